// Experiment (not built with the package): the whole 1 ms frame as ONE cooperative launch,
// with grid-wide or cluster barriers between substeps, timed against the production
// kernel-per-substep CUDA graphs. Results and verdict: docs/benchmarks/gpu-lab-2026-11-21.md
// Build: nvcc -O3 -std=c++17 --expt-relaxed-constexpr -arch=sm_90 -DCB_FRAME_BLOCK=256 \
//          -Inative tools/lab/frame_kernel.cu -o frame_kernel   (add big as argv[1] for n >= 1024)
// One 1 ms frame of the CUDA backend as a single cooperative launch: every substep of the
// frame, the ball and the per-frame read-back, with grid-wide barriers between substeps
// instead of one kernel launch each (a launch boundary costs ~2 us on an H100, more than a
// small cloth's whole substep).
#include <cooperative_groups.h>

#include "core/forces.hpp"

namespace cb {

#ifndef CB_FRAME_BLOCK
#define CB_FRAME_BLOCK 512
#endif
constexpr int kFrameBlock = CB_FRAME_BLOCK;
// Per-frame read-back: 4 corners (position, velocity), the ball (position, velocity) and
// the non-finite flag, written to mapped host memory.
constexpr int kReadback = 4 * 6 + 6 + 1;
constexpr int kReadbackFlag = 30;

template <class R>
struct DevBuf {
  Planes<R> pos, vel;
};

template <class R>
__device__ R warp_sum(R v) {
  for (int o = 16; o > 0; o >>= 1) v += __shfl_down_sync(0xffffffffu, v, o);
  return v;
}

// The block's sum of v, valid in thread 0.
template <class R>
__device__ V3<R> block_sum(V3<R> v) {
  __shared__ R red[3][kFrameBlock / 32];
  const int lane = threadIdx.x & 31, warp = threadIdx.x >> 5;
  const R c[3] = {warp_sum(v.x), warp_sum(v.y), warp_sum(v.z)};
  if (lane == 0)
    for (int k = 0; k < 3; ++k) red[k][warp] = c[k];
  __syncthreads();
  V3<R> s{R(0), R(0), R(0)};
  if (threadIdx.x == 0)
    for (int w = 0; w < kFrameBlock / 32; ++w) s += V3<R>{red[0][w], red[1][w], red[2][w]};
  __syncthreads();  // red is reused by the next call
  return s;
}

template <class R>
struct FrameArgs {
  Params<R> p;
  DevBuf<R> buf[2];
  Planes<R> scratch;           // strain limiting's second position buffer
  Ball<R>* ball;               // one slot per buffer
  R* acc;                      // 3 slots of 4: the ball's contact sums, round-robin
  int* nonfinite;              // sticky until the host resets the state
  const FrameInputs<R>* fin;   // mapped host memory: the hands and the wind
  R* readback;                 // mapped host memory, kReadback values
  int start, substeps, sweeps, acc_base;
  int cluster;                 // 1: the grid is one thread-block cluster (cheaper barrier)
  R dt;
};

// Semi-implicit Euler for a whole frame (eqs. 1-7), launched cooperatively so that the
// grid-wide barrier is legal. Each substep: every node from buffer b into 1 - b, each block
// adds its nodes' contact forces into a slot; barrier; every block then integrates the ball
// from that sum itself (the same arithmetic everywhere, so all blocks agree without a
// broadcast). Contact slots rotate over three: slot s is summed before barrier s and read
// after it, and block 0 clears slot s + 2 after barrier s, which no block touches again
// until after barrier s + 1. acc_base carries the rotation across frames.
template <class R, unsigned E>
__global__ void __launch_bounds__(kFrameBlock) frame_kernel(FrameArgs<R> a) {
  namespace cg = cooperative_groups;
  // One barrier for the whole grid: a hardware cluster barrier when the grid is a single
  // cluster (small cloths), else the cooperative grid barrier.
  auto barrier = [&]() {
    if (a.cluster) cg::this_cluster().sync();
    else cg::this_grid().sync();
  };
  __shared__ FrameInputs<R> fin;
  if (threadIdx.x == 0) fin = *a.fin;
  __syncthreads();
  const Params<R> p = a.p;
  const int n = p.n, nodes = n * n;
  const int first = blockIdx.x * blockDim.x + threadIdx.x, stride = gridDim.x * blockDim.x;
  const R dt = a.dt;
  int b = a.start;
  Ball<R> ball = a.ball[b];
  R check = 0;  // t - t of every value written: 0 while all are finite
  for (int s = 0; s < a.substeps; ++s) {
    const DevBuf<R> in = a.buf[b], out = a.buf[1 - b];
    V3<R> contact{R(0), R(0), R(0)};
    for (int q = first; q < nodes; q += stride) {
      const int i = q / n, j = q - i * n;
      contact += se_node_update<R, E>(p, in.pos, in.vel, out.pos, out.vel, fin, ball.p, i, j,
                                      dt, check);
    }
    R* acc = a.acc + 4 * ((a.acc_base + s) % 3);
    if constexpr ((E & BALL) != 0) {
      const V3<R> sum = block_sum(contact);
      if (threadIdx.x == 0) {
        if (sum.x != R(0)) atomicAdd(acc + 0, sum.x);
        if (sum.y != R(0)) atomicAdd(acc + 1, sum.y);
        if (sum.z != R(0)) atomicAdd(acc + 2, sum.z);
      }
    }
    if (check != R(0)) *a.nonfinite = 1;
    // Strain limiting: an even number of Jacobi sweeps, out.pos -> scratch -> out.pos.
    for (int k = 0; k < a.sweeps; ++k) {
      barrier();
      const Planes<R> A = (k % 2) ? a.scratch : out.pos, B = (k % 2) ? out.pos : a.scratch;
      for (int q = first; q < nodes; q += stride)
        strain_limit_node<R>(p, A, B, out.vel, q / n, q % n, R(1) / dt);
    }
    barrier();
    if constexpr ((E & BALL) != 0) {
      const volatile R* va = acc;  // summed by atomics in L2: read past L1
      ball = ball_update<R>(p, ball, V3<R>{va[0], va[1], va[2]}, dt);
      if (first == 0) {
        R* z = a.acc + 4 * ((a.acc_base + s + 2) % 3);
        z[0] = z[1] = z[2] = R(0);
      }
    }
    b = 1 - b;
  }
  // After the last barrier every node of buffer b is final: block 0 reports the frame.
  if (blockIdx.x == 0) {
    const int t = threadIdx.x;
    if (t < 4) {
      const int q = corner_node(t, n);
      const V3<R> x = a.buf[b].pos.get(q), v = a.buf[b].vel.get(q);
      R* o = a.readback + 6 * t;
      o[0] = x.x; o[1] = x.y; o[2] = x.z; o[3] = v.x; o[4] = v.y; o[5] = v.z;
    } else if (t == 4) {
      a.ball[b] = ball;
      R* o = a.readback + 24;
      o[0] = ball.p.x; o[1] = ball.p.y; o[2] = ball.p.z;
      o[3] = ball.v.x; o[4] = ball.v.y; o[5] = ball.v.z;
      o[6] = R(*a.nonfinite);
    }
  }
}

}  // namespace cb

// Lab: time frame_kernel alone for the classic effect set (not part of the build).
#include <cuda_runtime.h>

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <vector>

#include "core/params.hpp"

using namespace cb;
#define CK(x) do { cudaError_t e = (x); if (e != cudaSuccess) { printf("%s: %s\n", #x, cudaGetErrorString(e)); exit(1); } } while (0)

template <class R, unsigned E>
double run(int n, int S, int frames, int reps, int* blocks_out, int cluster) {
  Config c;
  c.n = n; c.rest_len = 1.0 / (n - 1); c.node_mass = 0.5 / (double(n) * n);
  c.k_struct = 2000; c.damping = 0.002; c.ball_radius = 0.08; c.ball_mass = 0.2;
  c.ball_k = 5000; c.ball_damping = 0.01; c.coupling_k = 1000; c.effects = E;
  const int N = n * n;
  R* state; CK(cudaMalloc(&state, sizeof(R) * 12 * N));
  std::vector<R> h(12 * size_t(N), R(0));
  for (int b = 0; b < 2; ++b)
    for (int i = 0; i < n; ++i)
      for (int j = 0; j < n; ++j) {
        int q = i * n + j;
        h[size_t(b) * 6 * N + q] = R(-0.5 + j * c.rest_len);
        h[size_t(b) * 6 * N + N + q] = R(1.0);
        h[size_t(b) * 6 * N + 2 * N + q] = R(-0.5 + i * c.rest_len);
      }
  CK(cudaMemcpy(state, h.data(), sizeof(R) * h.size(), cudaMemcpyHostToDevice));
  Ball<R>* ball; CK(cudaMalloc(&ball, 2 * sizeof(Ball<R>)));
  Ball<R> b0{{R(0), R(1.07), R(0)}, {R(0), R(0), R(0)}}; Ball<R> bb[2] = {b0, b0};
  CK(cudaMemcpy(ball, bb, sizeof(bb), cudaMemcpyHostToDevice));
  R* acc; CK(cudaMalloc(&acc, 12 * sizeof(R))); CK(cudaMemset(acc, 0, 12 * sizeof(R)));
  int* nf; CK(cudaMalloc(&nf, sizeof(int))); CK(cudaMemset(nf, 0, sizeof(int)));
  R* scratch; CK(cudaMalloc(&scratch, sizeof(R) * 3 * N));
  FrameInputs<R>* fh; CK(cudaHostAlloc(&fh, sizeof(FrameInputs<R>), cudaHostAllocMapped));
  R* rb; CK(cudaHostAlloc(&rb, sizeof(R) * kReadback, cudaHostAllocMapped));
  *fh = FrameInputs<R>{};
  for (int k = 0; k < 4; ++k) {
    int q = corner_node(k, n);
    fh->hips[k] = {h[q], h[N + q], h[2 * N + q]};
  }
  FrameInputs<R>* fd; R* rbd;
  CK(cudaHostGetDevicePointer(&fd, fh, 0)); CK(cudaHostGetDevicePointer(&rbd, rb, 0));
  auto fn = frame_kernel<R, E>;
  int occ = 0, sms = 0;
  CK(cudaOccupancyMaxActiveBlocksPerMultiprocessor(&occ, fn, kFrameBlock, 0));
  CK(cudaDeviceGetAttribute(&sms, cudaDevAttrMultiProcessorCount, 0));
  int blocks = std::min(occ * sms, (N + kFrameBlock - 1) / kFrameBlock);
  if (cluster) {
    blocks = std::min(cluster, (N + kFrameBlock - 1) / kFrameBlock);
    CK(cudaFuncSetAttribute((void*)fn, cudaFuncAttributeNonPortableClusterSizeAllowed, 1));
  }
  *blocks_out = blocks;
  cudaStream_t st; CK(cudaStreamCreateWithFlags(&st, cudaStreamNonBlocking));
  int cur = 0, base = 0;
  auto frame = [&]() {
    FrameArgs<R> a;
    a.p = Params<R>::from(c);
    for (int k = 0; k < 2; ++k) {
      R* d = state + size_t(k) * 6 * N;
      a.buf[k] = {{d, d + N, d + 2 * N}, {d + 3 * N, d + 4 * N, d + 5 * N}};
    }
    a.scratch = {scratch, scratch + N, scratch + 2 * N};
    a.ball = ball; a.acc = acc; a.nonfinite = nf; a.fin = fd; a.readback = rbd;
    a.start = cur; a.substeps = S; a.sweeps = 0; a.acc_base = base; a.dt = R(1e-3 / S);
    a.cluster = cluster ? 1 : 0;
    if (cluster) {
      cudaLaunchConfig_t cfg = {};
      cfg.gridDim = dim3(blocks); cfg.blockDim = dim3(kFrameBlock); cfg.stream = st;
      cudaLaunchAttribute at[1];
      at[0].id = cudaLaunchAttributeClusterDimension;
      at[0].val.clusterDim.x = blocks; at[0].val.clusterDim.y = 1; at[0].val.clusterDim.z = 1;
      cfg.attrs = at; cfg.numAttrs = 1;
      CK(cudaLaunchKernelEx(&cfg, fn, a));
    } else {
      void* args[] = {&a};
      CK(cudaLaunchCooperativeKernel((void*)fn, blocks, kFrameBlock, args, 0, st));
    }
    if (S % 2) cur = 1 - cur;
    base = (base + S) % 3;
  };
  for (int k = 0; k < 3; ++k) frame();
  CK(cudaStreamSynchronize(st));
  std::vector<double> t;
  for (int r = 0; r < reps; ++r) {
    auto t0 = std::chrono::steady_clock::now();
    for (int f = 0; f < frames; ++f) frame();
    CK(cudaStreamSynchronize(st));
    auto t1 = std::chrono::steady_clock::now();
    t.push_back(std::chrono::duration<double, std::micro>(t1 - t0).count() / (frames * S));
  }
  std::sort(t.begin(), t.end());
  if (rb[30] != 0) printf("  NONFINITE!\n");
  cudaFree(state); cudaFree(ball); cudaFree(acc); cudaFree(nf); cudaFree(scratch);
  cudaFreeHost(fh); cudaFreeHost(rb); cudaStreamDestroy(st);
  return t[t.size() / 2];
}

int main(int argc, char** argv) {
  size_t bytes = size_t(1) << 30;
  char *x, *y; CK(cudaMalloc(&x, bytes)); CK(cudaMalloc(&y, bytes));
  cudaEvent_t e0, e1; cudaEventCreate(&e0); cudaEventCreate(&e1);
  std::vector<float> ms;
  for (int r = 0; r < 7; ++r) {
    cudaEventRecord(e0); cudaMemcpy(y, x, bytes, cudaMemcpyDeviceToDevice); cudaEventRecord(e1);
    cudaEventSynchronize(e1); float m; cudaEventElapsedTime(&m, e0, e1); ms.push_back(m);
  }
  std::sort(ms.begin(), ms.end());
  double copy = 2.0 * bytes / (ms[3] * 1e-3) / 1e9;
  cudaFree(x); cudaFree(y);
  cudaFuncAttributes fa; cudaFuncGetAttributes(&fa, frame_kernel<float, 121>);
  printf("block %d copy %.0f GB/s classic f32 regs %d spill %zu\n", kFrameBlock, copy, fa.numRegs, fa.localSizeBytes);
  const int ns[] = {25, 50, 60, 100, 135, 200, 256, 1024, 4096};
  const int ss[] = {4, 7, 8, 13, 18, 26, 34, 134, 548};
  const bool big = argc > 1;
  for (int k = 0; k < 9; ++k) {
    int n = ns[k], S = ss[k], blocks = 0;
    if (n > 256 && !big) break;
    int frames = n <= 256 ? 400 : n <= 1024 ? 20 : 2;
    double g = run<float, 121>(n, S, frames, 7, &blocks, 0);
    double gbs = 12.0 * 4 * double(n) * n / (g * 1e-6) / 1e9;
    printf("n %5d S %4d grid blocks %4d f32 %.3f us (%.0f%% copy)", n, S, blocks, g, 100 * gbs / copy);
    if (n <= 256) {
      double c8 = run<float, 121>(n, S, frames, 7, &blocks, 8);
      double c16 = run<float, 121>(n, S, frames, 7, &blocks, 16);
      double e16 = run<float, 73>(n, S, frames, 7, &blocks, 16);
      double e0 = run<float, 0>(n, S, frames, 7, &blocks, 16);
      printf(" | cl8 %.3f cl16 %.3f | noball16 %.3f none16 %.3f", c8, c16, e16, e0);
    }
    printf("\n");
  }
  return 0;
}
