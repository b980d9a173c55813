// The CUDA units' reductions, defined once: the block size, warp sums, grid-wide sums with
// one atomic per block and value, and the last-block pattern that lets the block that
// finishes last act on the totals within the same launch.
#pragma once
#include <cuda_runtime.h>

#include "core/vec.hpp"

namespace cb {
namespace ci {

constexpr int kBlock = 256;

inline unsigned grid_blocks(int entries, int max_blocks) {
  const int b = (entries + kBlock - 1) / kBlock;
  return unsigned(b < max_blocks ? b : max_blocks);
}

template <class R>
__device__ R warp_sum(R v) {
  for (int o = 16; o > 0; o >>= 1) v += __shfl_down_sync(0xffffffffu, v, o);
  return v;
}

// Adds this block's sums of v[0..K) to acc[0..K). With a ticket, returns true in thread 0
// of the block that finished last: acc then holds the grid's totals (read them through
// acc_read), and that thread must reset acc and *ticket to 0 for the next launch.
template <class R, int K>
__device__ bool grid_sum(const R (&v)[K], R* acc, unsigned* ticket) {
  __shared__ R red[K][kBlock / 32];
  __shared__ bool last;
  const int lane = threadIdx.x & 31, warp = threadIdx.x >> 5;
#pragma unroll
  for (int k = 0; k < K; ++k) {
    const R s = warp_sum(v[k]);
    if (lane == 0) red[k][warp] = s;
  }
  __syncthreads();
  if (threadIdx.x == 0) {
    for (int k = 0; k < K; ++k) {
      R s = R(0);
      for (int w = 0; w < kBlock / 32; ++w) s += red[k][w];
      if (s != R(0)) atomicAdd(&acc[k], s);
    }
    last = false;
    if (ticket) {
      __threadfence();
      last = atomicAdd(ticket, 1u) == gridDim.x - 1;
      if (last) __threadfence();
    }
  }
  __syncthreads();
  return last && threadIdx.x == 0;
}

template <class R>
__device__ R acc_read(const R* acc, int k) {
  return static_cast<const volatile R*>(acc)[k];
}

}  // namespace ci
}  // namespace cb
