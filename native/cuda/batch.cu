// Compiled once per real type: CB_REAL is float or double (see native/CMakeLists.txt).
// The batch's kernels (cuda/cloth.cu's CudaBatch launches them): every slot of a ClothBatch
// in one launch, each slot's arguments read from a device table (SlotDev) at its block
// index. The bodies are cuda/substep.cuh's, the lone cloth's own: one copy of the
// equations. A unit of its own so that it compiles beside cloth.cu (every effect set is a
// specialisation here too); built with cloth.cu's flags, so a slot computes as a lone cloth.
#include <cuda_runtime.h>

#include <array>

#include "core/backend.hpp"
#include "cuda/reduce.cuh"
#include "cuda/substep.cuh"

namespace cb {
namespace {

// All slots' frame inputs, from their rows of the batch's mapped array: a thread a slot.
template <class R>
__global__ void batch_load(const SlotDev<R>* __restrict__ table, int m) {
  follow_previous_launch();  // lets the first substep launch early (it waits for this)
  const int k = int(blockIdx.x * blockDim.x + threadIdx.x);
  if (k < m) *table[k].fin = *table[k].fin_src;
}

// Substep k of the frame for every slot: `blocks` blocks a slot, slot-major, each slot
// reading table buffer b and writing 1 - b, as its lone cloth's se_substep.
template <class R, unsigned E>
__global__ void __launch_bounds__(ci::kBlock)
    batch_substep(Params<R> p, const SlotDev<R>* __restrict__ table, int blocks, int k, int b,
                  R dt) {
  follow_previous_launch();
  const int slot = int(blockIdx.x) / blocks;
  const SlotDev<R>& s = table[slot];
  const int N = p.n * p.n;
  const SubstepBall<R> sb = substep_ball_at(s.ball[b], s.ball[1 - b], s.ring, s.ctl, k);
  se_substep_body<R, E>(p, dev_buf(s.state[b], N), dev_buf(s.state[1 - b], N), s.fin, sb,
                        s.nonfinite, dt, int(blockIdx.x) - slot * blocks, blocks);
}

// The frame's end for every slot, a block of 32 threads each (as the lone finish_frame):
// with the ball the last substep's update is still due.
template <class R, unsigned E>
__global__ void batch_finish(Params<R> p, const SlotDev<R>* __restrict__ table, int substeps,
                             int b, R dt) {
  follow_previous_launch();
  const SlotDev<R>& s = table[blockIdx.x];
  const int k = (E & BALL) != 0 ? substeps : 0;
  const SubstepBall<R> sb = substep_ball_at(s.ball[b], s.ball[1 - b], s.ring, s.ctl, k);
  finish_body<R, E>(p, dev_buf(s.state[b], p.n * p.n), sb, s.nonfinite, dt, s.readback,
                    int(threadIdx.x));
}

template <class R>
struct BatchEntry {
  template <unsigned E>
  struct At {
    // The frame's end depends on the set only through the ball (as cloth.cu).
    static constexpr BatchKernels<R> fn{&batch_load<R>, &batch_substep<R, E>,
                                        &batch_finish<R, E & BALL>};
  };
};

}  // namespace

template <>
const std::array<BatchKernels<CB_REAL>, kNumEffectSets>& batch_kernel_table<CB_REAL>() {
#ifdef CB_LAB_EFFECT_SET
  // A lab build (tools/lab/substep_bench.cu) compiles only the set it times.
  static std::array<BatchKernels<CB_REAL>, kNumEffectSets> t{};
  constexpr unsigned kLab = (CB_LAB_EFFECT_SET) & (kNumEffectSets - 1);  // its compiled bits
  t[kLab] = BatchEntry<CB_REAL>::template At<kLab>::fn;
  return t;
#else
  return dispatch_table<BatchKernels<CB_REAL>, BatchEntry<CB_REAL>::template At>();
#endif
}

}  // namespace cb
