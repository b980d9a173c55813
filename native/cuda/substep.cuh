// The semi-implicit Euler substep and the frame's end as device functions, shared by the
// lone cloth's kernels (cuda/cloth.cu: one cloth a launch) and the batch's kernels
// (cuda/batch.cu: every slot of a ClothBatch in one launch), so both run one copy of the
// equations. Included by .cu files only.
#pragma once
#include <cuda_runtime.h>

#include <array>
#include <cstring>
#include <limits>
#include <type_traits>
#include <utility>

#include "core/forces.hpp"
#include "core/params.hpp"
#include "core/tiled_plan.hpp"
#include "cuda/check.hpp"
#include "cuda/reduce.cuh"

namespace cb {

// Per-frame readback: 4 corners (position, velocity), the ball (position, velocity), a flag.
constexpr int kReadback = 4 * 6 + 6 + 1;  // + the non-finite flag

template <class R>
struct DevBuf {
  Planes<R> pos, vel;
};

// One state buffer of 6 planes (x y z vx vy vz) of N values each.
template <class R>
__host__ __device__ inline DevBuf<R> dev_buf(R* d, int N) {
  return {{d, d + N, d + 2 * size_t(N)}, {d + 3 * size_t(N), d + 4 * size_t(N), d + 5 * size_t(N)}};
}

// A non-negative real as an unsigned integer of its width: the integers order as the reals
// do, so atomicMin on them takes the minimum distance.
template <class R>
struct RealBits {
  using T = std::conditional_t<sizeof(R) == 4, unsigned, unsigned long long>;
  static __host__ __device__ T of(R v) {
    T b;
    std::memcpy(&b, &v, sizeof b);
    return b;
  }
  static __host__ __device__ R real(T b) {
    R v;
    std::memcpy(&v, &b, sizeof v);
    return v;
  }
};

// Nodes are reported to the ball's nearest-distance sum only within twice its radius: the
// test of contact_possible then stays exact while the ball moves less than its radius in a
// substep (every node is then >= 2r - r from it), and is on (conservative) beyond. Warps
// far from the ball so skip their atomic on the one shared word (thousands of blocks
// serialised on it at large n).
template <class R>
__host__ __device__ R near_cutoff2(const Params<R>& p) {
  const R c = R(2) * p.ball_radius;
  return c * c;
}

// One substep's ball sums: the contact force on the ball and the squared distance from the
// nearest node (after its update) to the ball's centre (before the ball's update), or the
// cutoff when no node is nearer.
template <class R>
struct BallAcc {
  R f[3];
  typename RealBits<R>::T nearest2;

  static __host__ __device__ BallAcc zero(const Params<R>& p) {
    return {{R(0), R(0), R(0)}, RealBits<R>::of(near_cutoff2(p))};
  }
};

// What outlives a frame: whether the frame's first substep computes contact.
struct BallCtl {
  int contact_on;      // may a node touch the ball in the next substep?
  int strain_limited;  // set by the host: strain limiting keeps contact on
};

// The ball's buffers as one launch sees them. Substep k of a frame reads the state buffer b
// and the ball slot b (`cur`); its sums go to ring[k % 3] (`acc`), the previous substep's
// are ring[(k - 1) % 3] (`acc_prev`, beside the ball slot 1 - b, `prev`).
template <class R>
struct SubstepBall {
  const Ball<R>* prev;         // the previous substep's ball; null: the frame's first substep
  const BallAcc<R>* acc_prev;  // the previous substep's sums
  Ball<R>* cur;                // this substep's ball: read when prev is null, else written
  Ball<R>* next;               // no ball effect: where the unchanged ball is carried
  BallAcc<R>* acc;             // this substep's sums
  BallAcc<R>* acc_next;        // cleared for the launch after next
  BallAcc<R>* ring;            // all three (the frame's end clears them)
  BallCtl* ctl;
};

// Substep k of a frame whose state buffer b goes with ball `cur` (the other buffer's ball:
// `other`); k = substeps: the frame's end.
template <class R>
__host__ __device__ inline SubstepBall<R> substep_ball_at(Ball<R>* cur, Ball<R>* other,
                                                          BallAcc<R>* ring, BallCtl* ctl, int k) {
  return {k == 0 ? nullptr : other, ring + (k + 2) % 3, cur, other,
          ring + k % 3, ring + (k + 1) % 3, ring, ctl};
}

// The ball at the start of a substep, and whether that substep computes contact.
template <class R>
struct BallNow {
  Ball<R> b;
  bool touch;
};

// The ball's update for the previous substep, deferred to here (eqs. 5-6): every block of a
// substep computes it alike from the previous substep's finished sums, so no block waits
// for the others inside a launch (no last-block ticket); the launch boundary is the barrier.
// `prev` null: the first substep of a frame, whose ball the last frame finished.
template <class R>
__device__ BallNow<R> ball_now(const Params<R>& p, const Ball<R>* prev, const BallAcc<R>* acc,
                               const Ball<R>* cur, const BallCtl* ctl, R dt) {
  if (prev == nullptr) return {*cur, ctl->contact_on != 0};
  const Ball<R> b0 = *prev;
  const V3<R> sum{acc->f[0], acc->f[1], acc->f[2]};
  const Ball<R> b = ball_update<R>(p, b0, sum, dt);
  return {b, contact_possible(p, RealBits<R>::real(acc->nearest2), b.p - b0.p,
                              ctl->strain_limited != 0)};
}

// Programmatic dependent launch (Hopper): a launch made programmatic (`launch_kernel`
// below) may start while the one before it still runs, hiding its launch latency, and
// waits here until that one's writes are visible. For any other launch both are no-ops.
__device__ inline void follow_previous_launch() {
#if defined(__CUDA_ARCH__) && __CUDA_ARCH__ >= 900
  asm volatile("griddepcontrol.launch_dependents;" ::: "memory");
  asm volatile("griddepcontrol.wait;" ::: "memory");
#endif
}

template <class R>
__device__ R warp_min(R v) {
  for (int o = 16; o > 0; o >>= 1) v = fmin(v, __shfl_down_sync(0xffffffffu, v, o));
  return v;
}

// A substep's ball, before its nodes: the ball brought up to this substep (ball_now; at
// large n a launch of its own did) and whether contact is on. The `leader` thread (one in
// the whole grid) stores the ball and clears the sums the launch after next will use
// (`acc_next`).
template <class R, unsigned E>
__device__ __forceinline__ BallNow<R> substep_ball_begin(const Params<R>& p,
                                                         const SubstepBall<R>& sb, R dt,
                                                         bool leader) {
  BallNow<R> now{{{R(0), R(0), R(0)}, {R(0), R(0), R(0)}}, false};
  if constexpr ((E & BALL) != 0) {
    now = ball_now<R>(p, sb.prev, sb.acc_prev, sb.cur, sb.ctl, dt);
    if (leader) {
      if (sb.prev != nullptr) *sb.cur = now.b;
      *sb.acc_next = BallAcc<R>::zero(p);
    }
  }
  return now;
}

// The kick of one node's substep (se_node_kick) from the views (P, V): its position at the
// substep's start in x, its new velocity in v. While no node can touch the ball (`touch`
// false, the same decision for the whole grid) it runs compiled without contact. Returns
// the node's contact force.
template <class R, unsigned E, class G>
__device__ __forceinline__ V3<R> se_kick_touch(const Params<R>& p, const G& P, const G& V,
                                               const FrameInputs<R>& fin, const BallNow<R>& now,
                                               int i, int j, R dt, V3<R>& x, V3<R>& v) {
  if constexpr ((E & BALL) != 0) {
    if (now.touch) return se_node_kick<R, E>(p, P, V, fin, now.b.p, i, j, dt, x, v);
    se_node_kick<R, (E & ~BALL)>(p, P, V, fin, now.b.p, i, j, dt, x, v);
    return {R(0), R(0), R(0)};
  } else {
    return se_node_kick<R, E>(p, P, V, fin, now.b.p, i, j, dt, x, v);
  }
}

// The squared distance of the node nearest the ball (`near2`, for contact_possible), given
// a node's new position x.
template <class R, unsigned E>
__device__ __forceinline__ void track_nearest(const BallNow<R>& now, V3<R> x, R& near2) {
  if constexpr ((E & BALL) != 0) {
    const V3<R> d = x - now.b.p;
    near2 = fmin(near2, dot(d, d));
  }
}

// The drift of the node's substep (x to its new position), with its finite check and
// track_nearest.
template <class R, unsigned E>
__device__ __forceinline__ void se_drift_tracked(const BallNow<R>& now, V3<R>& x, V3<R> v, R dt,
                                                 R& check, R& near2) {
  euler_drift(x, v, dt);
  check_finite(check, x, v);
  track_nearest<R, E>(now, x, near2);
}

// A node's whole substep (se_node_step: kick and drift) from the views (P, V), compiled
// without contact while no node can touch the ball, as se_kick_touch. Each branch is the
// whole step, so that without contact it is the very code of a scene without a ball (bit
// for bit: split at the kick, the two kernels' drifts were contracted differently).
template <class R, unsigned E, class G>
__device__ __forceinline__ V3<R> se_step_touch(const Params<R>& p, const G& P, const G& V,
                                               const FrameInputs<R>& fin, const BallNow<R>& now,
                                               int i, int j, R dt, R& check, V3<R>& x, V3<R>& v) {
  if constexpr ((E & BALL) != 0) {
    if (now.touch) return se_node_step<R, E>(p, P, V, fin, now.b.p, i, j, dt, check, x, v);
    se_node_step<R, (E & ~BALL)>(p, P, V, fin, now.b.p, i, j, dt, check, x, v);
    return {R(0), R(0), R(0)};
  } else {
    return se_node_step<R, E>(p, P, V, fin, now.b.p, i, j, dt, check, x, v);
  }
}

// A substep's ball, after its nodes: each warp adds its nodes' contact forces and nearest
// distance to this substep's sums (`acc`), which the next substep reads; with no ball in
// the scene the `leader` carries its state unchanged. Whole warps must arrive.
template <class R, unsigned E>
__device__ __forceinline__ void substep_ball_end(const Params<R>& p, const SubstepBall<R>& sb,
                                                 V3<R> contact, R near2, bool leader) {
  if constexpr ((E & BALL) == 0) {
    if (leader) *sb.next = *sb.cur;  // no ball in this scene: carry its state unchanged
  } else {
    // Only the few warps at the ball have anything to add; the others skip the shuffles
    // too (the loops exit per lane, but every lane of a launched warp arrives).
    const unsigned all = 0xffffffffu;
    const bool lead = (threadIdx.x & 31) == 0;
    if (__any_sync(all, contact.x != R(0) || contact.y != R(0) || contact.z != R(0))) {
      const R c[3] = {ci::warp_sum(contact.x), ci::warp_sum(contact.y),
                      ci::warp_sum(contact.z)};
      if (lead)
        for (int k = 0; k < 3; ++k) atomicAdd(&sb.acc->f[k], c[k]);
    }
    if (__any_sync(all, near2 < near_cutoff2(p))) {
      near2 = warp_min(near2);
      if (lead) atomicMin(&sb.acc->nearest2, RealBits<R>::of(near2));
    }
  }
}

// One semi-implicit Euler substep for the nodes of one cloth, by its `blocks` blocks of
// which this thread's is `block` (a grid-stride loop over them, or one node a thread for
// the largest cloths, see CudaCloth::capture; each thread pays the ball's update once).
template <class R, unsigned E>
__device__ __forceinline__ void se_substep_body(Params<R> p, DevBuf<R> in,
                                                DevBuf<R> out,
                                                const FrameInputs<R>* __restrict__ fin,
                                                SubstepBall<R> sb, int* nonfinite, R dt,
                                                int block, int blocks) {
  const int n = p.n;
  const int first = block * blockDim.x + threadIdx.x;
  const BallNow<R> now = substep_ball_begin<R, E>(p, sb, dt, first == 0);
  V3<R> contact{R(0), R(0), R(0)};
  R check = 0;
  R near2 = std::numeric_limits<R>::infinity();
  for (int q = first; q < n * n; q += blocks * blockDim.x) {
    const int i = q / n, j = q - i * n;
    V3<R> x, v;
    contact += se_step_touch<R, E>(p, in.pos, in.vel, *fin, now, i, j, dt, check, x, v);
    track_nearest<R, E>(now, x, near2);
    out.pos.set(q, x);
    out.vel.set(q, v);
  }
  if (check != R(0)) *nonfinite = 1;  // sticky until the host resets the state
  substep_ball_end<R, E>(p, sb, contact, near2, first == 0);
}

// The end of a frame for one cloth, thread t of a block of 32 (a whole warp: every lane
// must arrive, as the grips' sums are shuffled): the last substep's deferred
// ball update (when `sb.prev` is set), then the corners, the ball and the non-finite flag to
// the mapped read-back. With no read-back (`out` null) it is the ball's own launch before
// a substep (large n).
template <class R, unsigned E>
__device__ __forceinline__ void finish_body(const Params<R>& p, const DevBuf<R>& s,
                                            const SubstepBall<R>& sb, const int* nonfinite, R dt,
                                            R* out, int t) {
  if (out != nullptr) {
    // The point each hand holds (grip_point), hand t / 8 by 8 lanes striding over its grip's
    // nodes: a grip of M nodes an edge (M ~ n / 10 for the shipped 10 cm) costs the frame's
    // end M / 8 loads' latency in turn, not M.
    const int c = t >> 3, lane = t & 7;
    V3<R> x, v;
    R total;
    grip_point_part(p, s.pos, s.vel, c, lane, 8, x, v, total);
    R sums[7] = {x.x, x.y, x.z, v.x, v.y, v.z, total};
    for (int o = 4; o > 0; o >>= 1)
      for (int k = 0; k < 7; ++k) sums[k] += __shfl_xor_sync(0xffffffffu, sums[k], o);
    if (lane == 0) {
      R* o = out + 6 * c;
      const R inv = R(1) / sums[6];
      for (int k = 0; k < 6; ++k) o[k] = sums[k] * inv;
    }
  }
  if (t == 0) {
    Ball<R> b = *sb.cur;
    if constexpr ((E & BALL) != 0) {
      if (sb.prev != nullptr) {
        const BallNow<R> now = ball_now<R>(p, sb.prev, sb.acc_prev, sb.cur, sb.ctl, dt);
        b = now.b;
        *sb.cur = b;
        sb.ctl->contact_on = now.touch ? 1 : 0;
        for (int k = 0; k < 3; ++k) sb.ring[k] = BallAcc<R>::zero(p);
      }
    }
    if (out == nullptr) return;
    R* o = out + 24;
    o[0] = b.p.x; o[1] = b.p.y; o[2] = b.p.z;
    o[3] = b.v.x; o[4] = b.v.y; o[5] = b.v.z;
    o[6] = R(*nonfinite);
  }
}

// A launch into a frame's graph that may overlap the one before it (see
// follow_previous_launch); an ordinary launch where `overlap` is off.
// `shared`: the launch's dynamic shared memory in bytes.
template <class... Ps, class... As>
void launch_kernel_shared(cudaStream_t stream, bool overlap, size_t shared,
                          void (*kernel)(Ps...), unsigned grid, unsigned block, As&&... args) {
  cudaLaunchConfig_t cfg{};
  cfg.gridDim = dim3(grid);
  cfg.blockDim = dim3(block);
  cfg.dynamicSmemBytes = shared;
  cfg.stream = stream;
  cudaLaunchAttribute attr{};
  attr.id = cudaLaunchAttributeProgrammaticStreamSerialization;
  attr.val.programmaticStreamSerializationAllowed = 1;
  cfg.attrs = &attr;
  cfg.numAttrs = overlap ? 1 : 0;
  CB_CUDA(cudaLaunchKernelEx(&cfg, kernel, std::forward<As>(args)...));
}

template <class... Ps, class... As>
void launch_kernel(cudaStream_t stream, bool overlap, void (*kernel)(Ps...), unsigned grid,
                   unsigned block, As&&... args) {
  launch_kernel_shared(stream, overlap, 0, kernel, grid, block, std::forward<As>(args)...);
}

// --- The batch: every slot of a ClothBatch in one launch (cuda/batch.cu) ----------------

// One slot's device state as the batch's kernels see it, with the buffer that is current
// when the table is built first (state[0] goes with ball[0]).
template <class R>
struct SlotDev {
  R* state[2];                    // two buffers of 6 planes
  Ball<R>* ball[2];
  BallAcc<R>* ring;               // three substeps' ball sums (SubstepBall)
  BallCtl* ctl;
  FrameInputs<R>* fin;            // the slot's device copy of its frame inputs
  const FrameInputs<R>* fin_src;  // its row of the batch's mapped inputs
  int* nonfinite;                 // sticky flag
  R* readback;                    // its row (kReadback values) of the mapped read-back
};

// Threads of the fused frame's block (one block a slot, its state in shared memory).
constexpr int kFusedBlock = 1024;

// The batch's kernels for one effect set. `b` is the table's buffer (0 or 1) a launch
// reads; the substep runs `blocks` blocks a slot, slot-major; `frame` runs a whole frame,
// a block a slot (substeps, then the frame's end).
template <class R>
struct BatchKernels {
  void (*load)(const SlotDev<R>*, int);
  void (*substep)(Params<R>, const SlotDev<R>*, int, int, int, R);
  void (*finish)(Params<R>, const SlotDev<R>*, int, int, R);
  void (*frame)(Params<R>, const SlotDev<R>*, int, int, R);
};

// One entry per effect set, as cloth.cu's kernel table (defined in cuda/batch.cu, once per
// real type).
template <class R>
const std::array<BatchKernels<R>, kNumEffectSets>& batch_kernel_table();
template <>
const std::array<BatchKernels<float>, kNumEffectSets>& batch_kernel_table<float>();
template <>
const std::array<BatchKernels<double>, kNumEffectSets>& batch_kernel_table<double>();

// --- The tiled frame: a lone large cloth's frame in one cooperative launch (cuda/tiled.cu) -

// Its arguments: the plan (core/tiled_plan.hpp) and the cloth's device state, as a launch
// a substep has it (the buffer the frame starts from, b0, goes with ball[b0]).
template <class R>
struct TiledArgs {
  Params<R> p;
  int tiles_x, th, tw, reach;  // TiledPlan's
  R* state;                    // two buffers of 6 planes
  Ball<R>* ball;               // two
  BallAcc<R>* ring;
  BallCtl* ctl;
  const FrameInputs<R>* fin;
  int* nonfinite;
  int substeps, b0;
  R dt;
};

template <class R>
using TiledFrameFn = void (*)(TiledArgs<R>);

// One entry per effect set; null where the set cannot run tiled (wind: tiled_capable).
template <class R>
const std::array<TiledFrameFn<R>, kNumEffectSets>& tiled_kernel_table();
template <>
const std::array<TiledFrameFn<float>, kNumEffectSets>& tiled_kernel_table<float>();
template <>
const std::array<TiledFrameFn<double>, kNumEffectSets>& tiled_kernel_table<double>();

}  // namespace cb
