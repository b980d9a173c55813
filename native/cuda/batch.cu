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

// A whole frame for every slot, a block a slot, where a slot's two state buffers fit in
// shared memory (CudaBatch::fused_bytes): the slot's current buffer is copied in, the
// substeps alternate between the two copies and meet at a block barrier instead of a launch
// boundary, every neighbour read is on chip, and the result is copied to the global buffer
// the frame ends in (the one the per-substep launches would have written last). Each
// substep is se_substep_body over the slot's nodes as one block of one (the lone cloth's
// arithmetic per node); the frame's end is batch_finish's.
template <class R, unsigned E>
__global__ void __launch_bounds__(kFusedBlock)
    batch_frame(Params<R> p, const SlotDev<R>* __restrict__ table, int substeps, int b0,
                R dt) {
  follow_previous_launch();
  extern __shared__ unsigned char shared_bytes[];
  R* sh = reinterpret_cast<R*>(shared_bytes);
  const SlotDev<R>& s = table[blockIdx.x];
  const int N = p.n * p.n, t = int(threadIdx.x);
  const size_t planes = 6 * size_t(N);
  const R* __restrict__ in = s.state[b0];
  for (size_t q = size_t(t); q < planes; q += blockDim.x) sh[q] = in[q];
  __syncthreads();
  int b = b0, c = 0;  // the buffer the slot's ball goes with; the shared copy read
  for (int k = 0; k < substeps; ++k) {
    const SubstepBall<R> sb = substep_ball_at(s.ball[b], s.ball[1 - b], s.ring, s.ctl, k);
    se_substep_body<R, E>(p, dev_buf(sh + planes * size_t(c), N),
                          dev_buf(sh + planes * size_t(1 - c), N), s.fin, sb, s.nonfinite, dt,
                          0, 1);
    __syncthreads();  // the substep's nodes, ball and sums are written
    b = 1 - b;
    c = 1 - c;
  }
  R* __restrict__ out = s.state[b];
  for (size_t q = size_t(t); q < planes; q += blockDim.x) out[q] = sh[planes * size_t(c) + q];
  __syncthreads();
  if (t < 32) {
    const int k = (E & BALL) != 0 ? substeps : 0;
    const SubstepBall<R> sb = substep_ball_at(s.ball[b], s.ball[1 - b], s.ring, s.ctl, k);
    finish_body<R, E & BALL>(p, dev_buf(out, N), sb, s.nonfinite, dt, s.readback, t);
  }
}

template <class R>
struct BatchEntry {
  template <unsigned E>
  struct At {
    // The frame's end depends on the set only through the ball (as cloth.cu).
    static constexpr BatchKernels<R> fn{&batch_load<R>, &batch_substep<R, E>,
                                        &batch_finish<R, E & BALL>, &batch_frame<R, E>};
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
