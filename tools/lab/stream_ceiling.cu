// Experiment (not built with the package): how much of the device-to-device copy bandwidth
// a substep can reach at large n with the production memory layout (6 planes read, 6
// written), and what the production node update reaches in the same launch shapes.
// Results and verdict: docs/benchmarks/gpu-lab-2026-11-21.md ("Large n").
// Build: nvcc -O3 -std=c++17 --expt-relaxed-constexpr -arch=sm_90 -Inative \
//          tools/lab/stream_ceiling.cu -o stream_ceiling && ./stream_ceiling
#include <cstdio>
#include <vector>
#include <algorithm>

#include "core/forces.hpp"

using namespace cb;
using R = float;
constexpr int kBlock = 256;
constexpr unsigned kSet = STRUCTURAL | GRAVITY | DAMPING | COUPLING;  // classic, no ball

#define CK(x) do { cudaError_t e = (x); if (e != cudaSuccess) { \
  std::printf("%s: %s\n", #x, cudaGetErrorString(e)); std::exit(1); } } while (0)

struct Buf { Planes<R> pos, vel; };

// The layout's ceiling: each node reads its 6 values and writes 6 (no neighbours).
__global__ void copy12(int N, Buf in, Buf out, int stride_blocks) {
  for (int q = blockIdx.x * blockDim.x + threadIdx.x; q < N; q += stride_blocks * blockDim.x) {
    V3<R> x = in.pos.get(q), v = in.vel.get(q);
    out.pos.set(q, x * R(1.0001));
    out.vel.set(q, v * R(0.9999));
  }
}

// The production node update (semi-implicit Euler, classic without the ball).
template <bool Reload>
__global__ void __launch_bounds__(kBlock) node(Params<R> p, Buf in, Buf out,
                                               const FrameInputs<R>* fin, R dt, int stride_blocks,
                                               R* sink) {
  const int n = p.n;
  R check = 0, near2 = R(1e30);
  for (int q = blockIdx.x * blockDim.x + threadIdx.x; q < n * n; q += stride_blocks * blockDim.x) {
    const int i = q / n, j = q - i * n;
    se_node_update<R, kSet>(p, in.pos, in.vel, out.pos, out.vel, *fin, V3<R>{0, 0, 0}, i, j, dt,
                            check);
    if (Reload) {  // production's nearest-node tracking reads the new position back
      const V3<R> d = out.pos.get(q);
      near2 = fmin(near2, dot(d, d));
    }
  }
  if (check != R(0) || near2 < R(-1)) *sink = check + near2;
}

template <class F>
float time_us(F launch, int reps) {
  cudaEvent_t a, b;
  CK(cudaEventCreate(&a)); CK(cudaEventCreate(&b));
  std::vector<float> t;
  for (int r = 0; r < 5; ++r) {
    launch(0);
    CK(cudaEventRecord(a));
    for (int k = 0; k < reps; ++k) launch(k);
    CK(cudaEventRecord(b));
    CK(cudaEventSynchronize(b));
    float ms; CK(cudaEventElapsedTime(&ms, a, b));
    t.push_back(ms * 1000.f / reps);
  }
  std::sort(t.begin(), t.end());
  return t[2];
}

int main() {
  int sms; CK(cudaDeviceGetAttribute(&sms, cudaDevAttrMultiProcessorCount, 0));
  for (int n : {1024, 2048, 4096}) {
    const size_t N = size_t(n) * n;
    R* mem; CK(cudaMalloc(&mem, sizeof(R) * 12 * N));
    CK(cudaMemset(mem, 0, sizeof(R) * 12 * N));
    auto buf = [&](int b) {
      R* d = mem + size_t(b) * 6 * N;
      return Buf{{d, d + N, d + 2 * N}, {d + 3 * N, d + 4 * N, d + 5 * N}};
    };
    // Rest positions so the springs do real work.
    std::vector<R> h(6 * N, R(0));
    const R L = R(1.0 / (n - 1));
    for (size_t q = 0; q < N; ++q) { h[q] = R(q % n) * L; h[2 * N + q] = R(q / n) * L; h[N + q] = 1; }
    CK(cudaMemcpy(mem, h.data(), sizeof(R) * 6 * N, cudaMemcpyHostToDevice));
    CK(cudaMemcpy(mem + 6 * N, h.data(), sizeof(R) * 6 * N, cudaMemcpyHostToDevice));
    Config c; c.n = n; c.rest_len = L; c.node_mass = 1e-4; c.k_struct = 100; c.damping = 0.01;
    c.coupling_k = 100; c.effects = kSet;
    const Params<R> p = Params<R>::from(c);
    FrameInputs<R>* fin; CK(cudaMalloc(&fin, sizeof(FrameInputs<R>)));
    CK(cudaMemset(fin, 0, sizeof(FrameInputs<R>)));
    R* sink; CK(cudaMalloc(&sink, sizeof(R)));
    const double bytes = 12.0 * sizeof(R) * N;  // the minimum a substep moves
    const float copy_us = time_us([&](int) {
      CK(cudaMemcpyAsync(mem + 6 * N, mem, sizeof(R) * 6 * N, cudaMemcpyDeviceToDevice)); }, 20);
    const double copy_gbs = bytes / copy_us / 1e3;
    std::printf("n = %d: device-to-device copy %.0f GB/s (read + write)\n", n, copy_gbs);
    int occ_copy = 0, occ0 = 0, occ1 = 0;
    CK(cudaOccupancyMaxActiveBlocksPerMultiprocessor(&occ_copy, copy12, kBlock, 0));
    CK(cudaOccupancyMaxActiveBlocksPerMultiprocessor(&occ0, node<false>, kBlock, 0));
    CK(cudaOccupancyMaxActiveBlocksPerMultiprocessor(&occ1, node<true>, kBlock, 0));
    const int all = int((N + kBlock - 1) / kBlock);
    auto report = [&](const char* what, float us) {
      std::printf("  %-46s %8.1f us  %6.0f GB/s  %3.0f%% of copy\n", what, us, bytes / us / 1e3,
                  100.0 * bytes / us / 1e3 / copy_gbs);
    };
    for (int grid : {all, 8 * sms, occ_copy * sms}) {
      char what[96];
      std::snprintf(what, sizeof what, "copy 6 planes in, 6 out, grid %d", grid);
      report(what, time_us([&](int k) {
        copy12<<<grid, kBlock>>>(int(N), buf(k & 1), buf(1 - (k & 1)), grid); }, 20));
    }
    std::printf("  (blocks resident per SM: copy %d, node %d, node+reload %d)\n", occ_copy, occ0,
                occ1);
    for (int grid : {all, 8 * sms, occ0 * sms}) {
      char what[96];
      std::snprintf(what, sizeof what, "node update, grid %d", grid);
      report(what, time_us([&](int k) {
        node<false><<<grid, kBlock>>>(p, buf(k & 1), buf(1 - (k & 1)), fin, R(1e-5), grid, sink); }, 20));
      std::snprintf(what, sizeof what, "node update + reload, grid %d", grid);
      report(what, time_us([&](int k) {
        node<true><<<grid, kBlock>>>(p, buf(k & 1), buf(1 - (k & 1)), fin, R(1e-5), grid, sink); }, 20));
    }
    CK(cudaFree(mem)); CK(cudaFree(fin)); CK(cudaFree(sink));
  }
}
