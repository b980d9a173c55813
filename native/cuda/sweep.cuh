// The sweep (core/sweep.hpp: each spring's force once) on the GPU: the lanes' exchange as
// warp shuffles, and a fused frame's substep through it. Included by .cu files only
// (cuda/tiled.cu, cuda/batch.cu).
#pragma once
#include <cuda_runtime.h>

#include <limits>

#include "core/sweep.hpp"
#include "cuda/substep.cuh"

namespace cb {

// The lanes' exchange of core/sweep.hpp's sweep_region: lane l gets lane l - d's (up) or
// l + d's (down) value.
struct WarpShuffle {
  template <class R>
  static __device__ __forceinline__ V3<R> up(V3<R> v, int d) {
    const unsigned all = 0xffffffffu;
    return {__shfl_up_sync(all, v.x, d), __shfl_up_sync(all, v.y, d),
            __shfl_up_sync(all, v.z, d)};
  }
  template <class R>
  static __device__ __forceinline__ V3<R> down(V3<R> v, int d) {
    const unsigned all = 0xffffffffu;
    return {__shfl_down_sync(all, v.x, d), __shfl_down_sync(all, v.y, d),
            __shfl_down_sync(all, v.z, d)};
  }
};

// se_substep_body's substep for one cloth by one whole block (a fused batch frame's slot),
// from buffer `in` to `out`, through the sweep; `plan` from sweep_plan over the whole cloth.
template <class R, unsigned E>
__device__ __forceinline__ void se_substep_sweep_body(const Params<R>& p, const DevBuf<R>& in,
                                                      const DevBuf<R>& out,
                                                      const FrameInputs<R>* __restrict__ fin,
                                                      const SubstepBall<R>& sb, int* nonfinite,
                                                      R dt, const SweepPlan& plan) {
  const int n = p.n, t = int(threadIdx.x);
  const BallNow<R> now = substep_ball_begin<R, E>(p, sb, dt, t == 0);
  V3<R> contact{R(0), R(0), R(0)};
  R check = 0;
  R near2 = std::numeric_limits<R>::infinity();
  const SweepRegion whole{0, n, 0, n, 0, n};
  sweep_region<R, E, WarpShuffle>(p, in.pos, whole, plan, t, [&](int i, int j, V3<R> springs) {
    V3<R> x, v;
    contact += se_step_touch<R, E, Planes<R>, false>(p, in.pos, in.vel, *fin, now, i, j, dt,
                                                     check, x, v, springs);
    track_nearest<R, E>(now, x, near2);
    const int q = i * n + j;
    out.pos.set(q, x);
    out.vel.set(q, v);
  });
  if (check != R(0)) *nonfinite = 1;  // sticky until the host resets the state
  substep_ball_end<R, E>(p, sb, contact, near2, t == 0);
}

}  // namespace cb
