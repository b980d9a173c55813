// CUDA backend: the shared core as one kernel per substep, the substeps of a frame captured
// in a CUDA graph. Per frame only the 4 corners and the ball are copied back; the mesh is
// copied only when asked for. This file never includes pybind11.
#include <cuda_runtime.h>

#include <algorithm>
#include <cstdio>
#include <map>
#include <tuple>
#include <stdexcept>
#include <string>
#include <vector>

#include "core/backend.hpp"
#include "core/forces.hpp"

namespace cb {
namespace {

#define CB_CUDA(call)                                                                  \
  do {                                                                                 \
    cudaError_t err_ = (call);                                                         \
    if (err_ != cudaSuccess)                                                           \
      throw std::runtime_error(std::string("CUDA error in ") + #call + ": " +          \
                               cudaGetErrorString(err_));                              \
  } while (0)

constexpr int kBlock = 256;

// Per-frame readback: 4 corners (position, velocity) then the ball (position, velocity).
constexpr int kReadback = 4 * 6 + 6;

template <class R>
struct DevBuf {
  Planes<R> pos, vel;
};

template <class R>
struct BallAcc {
  R f[3];
  unsigned ticket;
};

template <class R>
__device__ R warp_sum(R v) {
  for (int o = 16; o > 0; o >>= 1) v += __shfl_down_sync(0xffffffffu, v, o);
  return v;
}

// One semi-implicit Euler substep for every node. With the ball on, each block sums its
// nodes' contact forces; the last block to finish integrates the ball (eqs. 5-6), so the
// whole substep is a single launch.
template <class R, unsigned E>
__global__ void __launch_bounds__(kBlock) se_substep(Params<R> p, DevBuf<R> in, DevBuf<R> out,
                                                     const V3<R>* __restrict__ hips,
                                                     const Ball<R>* __restrict__ ball_in,
                                                     Ball<R>* __restrict__ ball_out,
                                                     BallAcc<R>* acc, R dt) {
  const int n = p.n;
  V3<R> contact{R(0), R(0), R(0)};
  V3<R> ball_p{R(0), R(0), R(0)};
  if constexpr ((E & BALL) != 0) ball_p = ball_in->p;
  // Grid-stride loop over a grid sized to the machine, not to the cloth: a large cloth then
  // needs one ball-sum atomic per resident block rather than one per 256 nodes.
  const int first = blockIdx.x * blockDim.x + threadIdx.x;
  for (int q = first; q < n * n; q += gridDim.x * blockDim.x) {
    const int i = q / n, j = q - i * n;
    V3<R> x = in.pos.get(q), v = in.vel.get(q), c{R(0), R(0), R(0)};
    V3<R> f = node_force<R, E>(p, in.pos, x, v, i, j, hips, ball_p, c);
    contact += c;
    euler_update(x, v, f, p.inv_mass, dt);
    out.pos.set(q, x);
    out.vel.set(q, v);
  }
  const int q = first;
  if constexpr ((E & BALL) == 0) {
    if (q == 0) *ball_out = *ball_in;  // no ball in this scene: carry its state unchanged
  }
  if constexpr ((E & BALL) != 0) {
    __shared__ R red[3][kBlock / 32];
    __shared__ bool last;
    R c[3] = {contact.x, contact.y, contact.z};
    const int lane = threadIdx.x & 31, warp = threadIdx.x >> 5;
#pragma unroll
    for (int k = 0; k < 3; ++k) {
      R s = warp_sum(c[k]);
      if (lane == 0) red[k][warp] = s;
    }
    __syncthreads();
    if (threadIdx.x == 0) {
      R s[3] = {R(0), R(0), R(0)};
      for (int w = 0; w < kBlock / 32; ++w)
        for (int k = 0; k < 3; ++k) s[k] += red[k][w];
      for (int k = 0; k < 3; ++k)
        if (s[k] != R(0)) atomicAdd(&acc->f[k], s[k]);
      __threadfence();
      last = atomicAdd(&acc->ticket, 1u) == gridDim.x - 1;
      if (last) {
        __threadfence();
        volatile R* vf = acc->f;
        V3<R> sum{vf[0], vf[1], vf[2]};
        *ball_out = ball_update<R, E>(p, *ball_in, sum, dt);
        acc->f[0] = acc->f[1] = acc->f[2] = R(0);
        acc->ticket = 0;
      }
    }
  }
}

template <class R>
__global__ void gather_corners(int n, DevBuf<R> s, const Ball<R>* ball, R* out) {
  const int t = threadIdx.x;
  if (t < 4) {
    const int last = n - 1;
    const int q = t == 0 ? 0 : t == 1 ? last : t == 2 ? n * n - 1 : last * n;
    V3<R> x = s.pos.get(q), v = s.vel.get(q);
    R* o = out + 6 * t;
    o[0] = x.x; o[1] = x.y; o[2] = x.z; o[3] = v.x; o[4] = v.y; o[5] = v.z;
  } else if (t == 4) {
    R* o = out + 24;
    o[0] = ball->p.x; o[1] = ball->p.y; o[2] = ball->p.z;
    o[3] = ball->v.x; o[4] = ball->v.y; o[5] = ball->v.z;
  }
}

template <class R>
__global__ void load_hips(const V3<R>* host_hips, V3<R>* dev_hips) {
  if (threadIdx.x < 4) dev_hips[threadIdx.x] = host_hips[threadIdx.x];
}

template <class R>
__global__ void normals_kernel(int n, Planes<R> pos, R* out) {
  const int q = blockIdx.x * blockDim.x + threadIdx.x;
  if (q >= n * n) return;
  V3<R> nr = node_normal(pos, n, q / n, q % n);
  out[3 * q] = nr.x; out[3 * q + 1] = nr.y; out[3 * q + 2] = nr.z;
}

template <class R>
using KernelFn = void (*)(Params<R>, DevBuf<R>, DevBuf<R>, const V3<R>*, const Ball<R>*,
                          Ball<R>*, BallAcc<R>*, R);

template <class R>
struct KernelEntry {
  template <unsigned E>
  struct At {
    static constexpr KernelFn<R> fn = &se_substep<R, E>;
  };
};

template <class R>
const std::array<KernelFn<R>, kNumEffectSets>& kernel_table() {
  static const auto t = effect_table<KernelFn<R>, KernelEntry<R>::template At>(
      std::make_integer_sequence<unsigned, kNumEffectSets>{});
  return t;
}

template <class R>
class CudaCloth final : public Backend {
 public:
  explicit CudaCloth(const Config& c) : n_(c.n), N_(c.n * c.n) {
    std::string why = cuda_unavailable_reason();
    if (!why.empty()) throw std::runtime_error("CUDA backend unavailable: " + why);
    CB_CUDA(cudaStreamCreateWithFlags(&stream_, cudaStreamNonBlocking));
    CB_CUDA(cudaMalloc(&state_, sizeof(R) * 12 * size_t(N_)));
    CB_CUDA(cudaMemset(state_, 0, sizeof(R) * 12 * size_t(N_)));
    CB_CUDA(cudaMalloc(&ball_, sizeof(Ball<R>) * 2));
    CB_CUDA(cudaMemset(ball_, 0, sizeof(Ball<R>) * 2));
    CB_CUDA(cudaMalloc(&acc_, sizeof(BallAcc<R>)));
    CB_CUDA(cudaMemset(acc_, 0, sizeof(BallAcc<R>)));
    CB_CUDA(cudaMalloc(&hips_dev_, sizeof(V3<R>) * 4));
    CB_CUDA(cudaMemset(hips_dev_, 0, sizeof(V3<R>) * 4));
    // Mapped pinned memory: kernels read the hands and write the per-frame read-back
    // directly, with no copy nodes in the frame's graph.
    CB_CUDA(cudaHostAlloc(&hips_host_, sizeof(V3<R>) * 4, cudaHostAllocMapped));
    CB_CUDA(cudaHostAlloc(&readback_host_, sizeof(R) * kReadback, cudaHostAllocMapped));
    CB_CUDA(cudaHostGetDevicePointer(&hips_mapped_, hips_host_, 0));
    CB_CUDA(cudaHostGetDevicePointer(&readback_mapped_, readback_host_, 0));
    int sms = 0;
    CB_CUDA(cudaDeviceGetAttribute(&sms, cudaDevAttrMultiProcessorCount, 0));
    max_blocks_ = sms * 8;
    for (int k = 0; k < 4; ++k) hips_host_[k] = {R(0), R(0), R(0)};
    for (int k = 0; k < kReadback; ++k) readback_host_[k] = R(0);
    configure(c);
  }

  ~CudaCloth() override {
    drop_graphs();
    cudaFree(state_); cudaFree(ball_); cudaFree(acc_); cudaFree(hips_dev_);
    cudaFreeHost(hips_host_); cudaFreeHost(readback_host_);
    cudaStreamDestroy(stream_);
  }

  void configure(const Config& c) override {
    if (c.n != n_) throw std::invalid_argument("configure: n cannot change");
    p_ = Params<R>::from(c);
    kernel_ = kernel_table<R>()[c.effects & (kNumEffectSets - 1)];
    drop_graphs();
  }

  void set_hips(const double* h) override {
    // Mapped pinned memory: the graph's first kernel reads it at every launch.
    for (int k = 0; k < 4; ++k) hips_host_[k] = {R(h[3 * k]), R(h[3 * k + 1]), R(h[3 * k + 2])};
  }

  void set_state(const double* pos, const double* vel) override {
    std::vector<R> h(6 * size_t(N_));
    for (int q = 0; q < N_; ++q)
      for (int d = 0; d < 3; ++d) {
        h[size_t(d) * N_ + q] = R(pos[3 * q + d]);
        h[size_t(3 + d) * N_ + q] = R(vel[3 * q + d]);
      }
    CB_CUDA(cudaMemcpy(buf(cur_), h.data(), sizeof(R) * h.size(), cudaMemcpyHostToDevice));
    refresh_readback();
  }
  void get_positions(double* out) override { copy_out(buf(cur_), out); }
  void get_velocities(double* out) override { copy_out(buf(cur_) + 3 * size_t(N_), out); }
  void get_normals(double* out) override {
    R* d = nullptr;
    CB_CUDA(cudaMallocAsync(&d, sizeof(R) * 3 * size_t(N_), stream_));
    normals_kernel<R><<<(N_ + kBlock - 1) / kBlock, kBlock, 0, stream_>>>(n_, dev(cur_).pos, d);
    CB_CUDA(cudaGetLastError());
    std::vector<R> h(3 * size_t(N_));
    CB_CUDA(cudaMemcpyAsync(h.data(), d, sizeof(R) * h.size(), cudaMemcpyDeviceToHost, stream_));
    CB_CUDA(cudaFreeAsync(d, stream_));
    CB_CUDA(cudaStreamSynchronize(stream_));
    for (size_t k = 0; k < h.size(); ++k) out[k] = h[k];
  }
  void set_ball(const double* pv) override {
    Ball<R> b{{R(pv[0]), R(pv[1]), R(pv[2])}, {R(pv[3]), R(pv[4]), R(pv[5])}};
    CB_CUDA(cudaMemcpy(ball_ + cur_, &b, sizeof(b), cudaMemcpyHostToDevice));
    refresh_readback();
  }
  void get_ball(double* pv) override {
    for (int k = 0; k < 6; ++k) pv[k] = readback_host_[24 + k];
  }
  void get_corners(double* out) override {
    for (int k = 0; k < 24; ++k) out[k] = readback_host_[k];
  }

  void step(int frames, int substeps, double dt) override {
    if (frames <= 0) return;
    for (int f = 0; f < frames; ++f) {
      // One graph per (substeps, dt, starting buffer): automatic substeps vary per frame.
      cudaGraphExec_t& g = graphs_[GraphKey{substeps, R(dt), cur_}];
      if (!g) g = capture(cur_, substeps, R(dt));
      CB_CUDA(cudaGraphLaunch(g, stream_));
      if (substeps % 2) cur_ = 1 - cur_;
    }
    CB_CUDA(cudaStreamSynchronize(stream_));
  }

 private:
  R* buf(int b) const { return state_ + size_t(b) * 6 * N_; }
  DevBuf<R> dev(int b) const {
    R* d = buf(b);
    return {{d, d + N_, d + 2 * size_t(N_)}, {d + 3 * size_t(N_), d + 4 * size_t(N_), d + 5 * size_t(N_)}};
  }

  // Capture one frame starting from buffer `start`: hips in, substeps, corners and ball out.
  cudaGraphExec_t capture(int start, int substeps, R dt) {
    cudaGraph_t graph;
    CB_CUDA(cudaStreamBeginCapture(stream_, cudaStreamCaptureModeThreadLocal));
    load_hips<R><<<1, 32, 0, stream_>>>(hips_mapped_, hips_dev_);
    int b = start;
    const unsigned blocks = unsigned(std::min((N_ + kBlock - 1) / kBlock, max_blocks_));
    for (int s = 0; s < substeps; ++s) {
      kernel_<<<blocks, kBlock, 0, stream_>>>(p_, dev(b), dev(1 - b), hips_dev_, ball_ + b,
                                             ball_ + (1 - b), acc_, dt);
      b = 1 - b;
    }
    gather_corners<R><<<1, 32, 0, stream_>>>(n_, dev(b), ball_ + b, readback_mapped_);
    CB_CUDA(cudaStreamEndCapture(stream_, &graph));
    cudaGraphExec_t exec;
    CB_CUDA(cudaGraphInstantiate(&exec, graph, 0));
    CB_CUDA(cudaGraphDestroy(graph));
    return exec;
  }

  void drop_graphs() {
    for (auto& kv : graphs_)
      if (kv.second) cudaGraphExecDestroy(kv.second);
    graphs_.clear();
  }

  void refresh_readback() {
    gather_corners<R><<<1, 32, 0, stream_>>>(n_, dev(cur_), ball_ + cur_, readback_mapped_);
    CB_CUDA(cudaGetLastError());
    CB_CUDA(cudaStreamSynchronize(stream_));
  }

  void copy_out(const R* planes, double* out) {
    std::vector<R> h(3 * size_t(N_));
    CB_CUDA(cudaMemcpy(h.data(), planes, sizeof(R) * h.size(), cudaMemcpyDeviceToHost));
    for (int q = 0; q < N_; ++q)
      for (int d = 0; d < 3; ++d) out[3 * q + d] = h[size_t(d) * N_ + q];
  }

  const int n_, N_;
  Params<R> p_{};
  KernelFn<R> kernel_ = nullptr;
  cudaStream_t stream_ = nullptr;
  R* state_ = nullptr;  // two buffers of 6 planes: x y z vx vy vz
  Ball<R>* ball_ = nullptr;
  BallAcc<R>* acc_ = nullptr;
  V3<R>* hips_dev_ = nullptr;
  V3<R>* hips_host_ = nullptr;
  V3<R>* hips_mapped_ = nullptr;  // device view of hips_host_
  R* readback_host_ = nullptr;
  R* readback_mapped_ = nullptr;  // device view of readback_host_
  int max_blocks_ = 1;
  int cur_ = 0;
  using GraphKey = std::tuple<int, R, int>;
  std::map<GraphKey, cudaGraphExec_t> graphs_;
};

}  // namespace

std::string cuda_unavailable_reason() {
  int count = 0;
  cudaError_t err = cudaGetDeviceCount(&count);
  if (err != cudaSuccess) {
    cudaGetLastError();
    return std::string("no usable CUDA device (") + cudaGetErrorString(err) + ")";
  }
  if (count == 0) return "no CUDA device found";
  return "";
}

double cuda_copy_bandwidth_gbs(size_t bytes, int reps) {
  std::string why = cuda_unavailable_reason();
  if (!why.empty()) throw std::runtime_error("CUDA unavailable: " + why);
  char *a = nullptr, *b = nullptr;
  CB_CUDA(cudaMalloc(&a, bytes));
  CB_CUDA(cudaMalloc(&b, bytes));
  CB_CUDA(cudaMemset(a, 1, bytes));
  cudaEvent_t t0, t1;
  CB_CUDA(cudaEventCreate(&t0));
  CB_CUDA(cudaEventCreate(&t1));
  std::vector<float> ms;
  for (int r = 0; r < reps + 2; ++r) {  // two warm-up copies
    CB_CUDA(cudaEventRecord(t0));
    CB_CUDA(cudaMemcpy(b, a, bytes, cudaMemcpyDeviceToDevice));
    CB_CUDA(cudaEventRecord(t1));
    CB_CUDA(cudaEventSynchronize(t1));
    float m = 0;
    CB_CUDA(cudaEventElapsedTime(&m, t0, t1));
    if (r >= 2) ms.push_back(m);
  }
  cudaEventDestroy(t0); cudaEventDestroy(t1); cudaFree(a); cudaFree(b);
  std::sort(ms.begin(), ms.end());
  // Bytes read plus bytes written, over the median time.
  return 2.0 * double(bytes) / (double(ms[ms.size() / 2]) * 1e-3) / 1e9;
}

std::unique_ptr<Backend> make_cuda_backend(const Config& c, bool dbl) {
  if (dbl) return std::make_unique<CudaCloth<double>>(c);
  return std::make_unique<CudaCloth<float>>(c);
}

}  // namespace cb
