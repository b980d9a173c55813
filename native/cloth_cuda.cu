// Compiled once per real type: CB_REAL is float or double (see native/CMakeLists.txt).
// CUDA backend: the shared core as one kernel per substep, the substeps of a frame captured
// in a CUDA graph. Per frame only the 4 corners and the ball are copied back; the mesh is
// copied only when asked for. This file never includes pybind11.
#include <cuda_runtime.h>

#include <algorithm>
#include <cstring>
#include <limits>
#include <cstdio>
#include <map>
#include <tuple>
#include <stdexcept>
#include <string>
#include <vector>

#include "core/backend.hpp"
#include "cuda_check.hpp"
#include "core/forces.hpp"
#include "cuda_integrators.hpp"

namespace cb {
namespace {


constexpr int kBlock = 256;

// Per-frame readback: 4 corners (position, velocity), the ball (position, velocity), a flag.
constexpr int kReadback = 4 * 6 + 6 + 1;  // + the non-finite flag

template <class R>
struct DevBuf {
  Planes<R> pos, vel;
};

// A non-negative real as an unsigned integer of its width: the integers order as the reals
// do, so atomicMin on them takes the minimum distance.
template <class R>
struct RealBits;
template <>
struct RealBits<float> {
  using T = unsigned;
  static __device__ T of(float v) { return __float_as_uint(v); }
  static __device__ float real(T b) { return __uint_as_float(b); }
};
template <>
struct RealBits<double> {
  using T = unsigned long long;
  static __device__ T of(double v) { return (T)__double_as_longlong(v); }
  static __device__ double real(T b) { return __longlong_as_double((long long)b); }
};

// The ball's per-substep accumulators, reset by the last block of each substep.
template <class R>
struct BallAcc {
  R f[3];
  unsigned ticket;
  typename RealBits<R>::T nearest2;  // smallest squared node-to-ball distance (see forces.hpp)
  int contact_on;                    // may a node touch the ball in the next substep?
  int strain_limited;                // set by the host: strain limiting keeps contact on

  static BallAcc initial(bool strain) {
    BallAcc a{};
    const R inf = std::numeric_limits<R>::infinity();
    std::memcpy(&a.nearest2, &inf, sizeof(R));
    a.contact_on = 1;
    a.strain_limited = strain ? 1 : 0;
    return a;
  }
};

template <class R>
__device__ R warp_sum(R v) {
  for (int o = 16; o > 0; o >>= 1) v += __shfl_down_sync(0xffffffffu, v, o);
  return v;
}

template <class R>
__device__ R warp_min(R v) {
  for (int o = 16; o > 0; o >>= 1) v = fmin(v, __shfl_down_sync(0xffffffffu, v, o));
  return v;
}

// One semi-implicit Euler substep for every node. With the ball on, each block sums its
// nodes' contact forces; the last block to finish integrates the ball (eqs. 5-6), so the
// whole substep is a single launch.
template <class R, unsigned E>
__global__ void __launch_bounds__(kBlock) se_substep(Params<R> p, DevBuf<R> in, DevBuf<R> out,
                                                     const FrameInputs<R>* __restrict__ fin,
                                                     const Ball<R>* __restrict__ ball_in,
                                                     Ball<R>* __restrict__ ball_out,
                                                     BallAcc<R>* acc, int* nonfinite, R dt) {
  const int n = p.n;
  V3<R> contact{R(0), R(0), R(0)};
  V3<R> ball_p{R(0), R(0), R(0)};
  if constexpr ((E & BALL) != 0) ball_p = ball_in->p;
  // Grid-stride loop over a grid sized to the machine, not to the cloth: a large cloth then
  // needs one ball-sum atomic per resident block rather than one per 256 nodes.
  const int first = blockIdx.x * blockDim.x + threadIdx.x;
  R check = 0;
  // While no node can touch the ball the sweep runs compiled without contact (the same
  // decision for the whole grid), still tracking the node nearest the ball.
  const bool touch = (E & BALL) != 0 && acc->contact_on;
  R near2 = std::numeric_limits<R>::infinity();
  for (int q = first; q < n * n; q += gridDim.x * blockDim.x) {
    const int i = q / n, j = q - i * n;
    if constexpr ((E & BALL) != 0) {
      if (touch)
        contact += se_node_update<R, E>(p, in.pos, in.vel, out.pos, out.vel, *fin, ball_p, i, j,
                                        dt, check);
      else
        se_node_update<R, (E & ~BALL)>(p, in.pos, in.vel, out.pos, out.vel, *fin, ball_p, i, j,
                                       dt, check);
      const V3<R> d = out.pos.get(q) - ball_p;
      near2 = fmin(near2, dot(d, d));
    } else {
      contact += se_node_update<R, E>(p, in.pos, in.vel, out.pos, out.vel, *fin, ball_p, i, j,
                                      dt, check);
    }
  }
  if (check != R(0)) *nonfinite = 1;  // sticky until the host resets the state
  const int q = first;
  if constexpr ((E & BALL) == 0) {
    if (q == 0) *ball_out = *ball_in;  // no ball in this scene: carry its state unchanged
  }
  if constexpr ((E & BALL) != 0) {
    __shared__ R red[4][kBlock / 32];
    __shared__ bool last;
    R c[3] = {contact.x, contact.y, contact.z};
    const int lane = threadIdx.x & 31, warp = threadIdx.x >> 5;
#pragma unroll
    for (int k = 0; k < 3; ++k) {
      R s = warp_sum(c[k]);
      if (lane == 0) red[k][warp] = s;
    }
    near2 = warp_min(near2);
    if (lane == 0) red[3][warp] = near2;
    __syncthreads();
    if (threadIdx.x == 0) {
      R s[4] = {R(0), R(0), R(0), red[3][0]};
      for (int w = 0; w < kBlock / 32; ++w) {
        for (int k = 0; k < 3; ++k) s[k] += red[k][w];
        s[3] = fmin(s[3], red[3][w]);
      }
      for (int k = 0; k < 3; ++k)
        if (s[k] != R(0)) atomicAdd(&acc->f[k], s[k]);
      atomicMin(&acc->nearest2, RealBits<R>::of(s[3]));
      __threadfence();
      last = atomicAdd(&acc->ticket, 1u) == gridDim.x - 1;
      if (last) {
        __threadfence();
        volatile BallAcc<R>* va = acc;
        const V3<R> sum{va->f[0], va->f[1], va->f[2]};
        const Ball<R> b = ball_update<R, E>(p, *ball_in, sum, dt);
        *ball_out = b;
        const R nearest2 = RealBits<R>::real(va->nearest2);
        acc->contact_on = contact_possible(p, nearest2, b.p - ball_in->p, va->strain_limited != 0);
        acc->f[0] = acc->f[1] = acc->f[2] = R(0);
        acc->nearest2 = RealBits<R>::of(std::numeric_limits<R>::infinity());
        acc->ticket = 0;
      }
    }
  }
}

template <class R>
__global__ void gather_corners(int n, DevBuf<R> s, const Ball<R>* ball, const int* nonfinite,
                               R* out) {
  const int t = threadIdx.x;
  if (t < 4) {
    const int q = corner_node(t, n);
    V3<R> x = s.pos.get(q), v = s.vel.get(q);
    R* o = out + 6 * t;
    o[0] = x.x; o[1] = x.y; o[2] = x.z; o[3] = v.x; o[4] = v.y; o[5] = v.z;
  } else if (t == 4) {
    R* o = out + 24;
    o[0] = ball->p.x; o[1] = ball->p.y; o[2] = ball->p.z;
    o[3] = ball->v.x; o[4] = ball->v.y; o[5] = ball->v.z;
    o[6] = R(*nonfinite);
  }
}

template <class R>
__global__ void load_inputs(const FrameInputs<R>* host, FrameInputs<R>* dev) {
  if (threadIdx.x == 0) *dev = *host;
}

// Strain limiting, half a pass: one thread per line (rows: first = i n, stride 1; columns:
// first = j, stride n), each a sequential follow-the-leader chain, in place.
template <class R>
__global__ void __launch_bounds__(kBlock) strain_kernel(Params<R> p, Planes<R> P, Planes<R> V,
                                                        int line_step, int stride, R inv_dt) {
  const int line = blockIdx.x * blockDim.x + threadIdx.x;
  if (line < p.n) strain_limit_line<R>(p, P, V, line * line_step, stride, inv_dt);
}

template <class R>
__global__ void normals_kernel(int n, Planes<R> pos, R* out) {
  const int q = blockIdx.x * blockDim.x + threadIdx.x;
  if (q >= n * n) return;
  V3<R> nr = node_normal(pos, n, q / n, q % n);
  out[3 * q] = nr.x; out[3 * q + 1] = nr.y; out[3 * q + 2] = nr.z;
}

template <class R>
using KernelFn = void (*)(Params<R>, DevBuf<R>, DevBuf<R>, const FrameInputs<R>*,
                          const Ball<R>*, Ball<R>*, BallAcc<R>*, int*, R);

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
    CB_CUDA(cudaMalloc(&fin_dev_, sizeof(FrameInputs<R>)));
    CB_CUDA(cudaMemset(fin_dev_, 0, sizeof(FrameInputs<R>)));
    CB_CUDA(cudaMalloc(&nonfinite_, sizeof(int)));
    CB_CUDA(cudaMemset(nonfinite_, 0, sizeof(int)));
    // Mapped pinned memory: kernels read the hands and write the per-frame read-back
    // directly, with no copy nodes in the frame's graph.
    CB_CUDA(cudaHostAlloc(&fin_host_, sizeof(FrameInputs<R>), cudaHostAllocMapped));
    CB_CUDA(cudaHostAlloc(&readback_host_, sizeof(R) * kReadback, cudaHostAllocMapped));
    CB_CUDA(cudaHostGetDevicePointer(&fin_mapped_, fin_host_, 0));
    CB_CUDA(cudaHostGetDevicePointer(&readback_mapped_, readback_host_, 0));
    int sms = 0;
    CB_CUDA(cudaDeviceGetAttribute(&sms, cudaDevAttrMultiProcessorCount, 0));
    max_blocks_ = sms * 8;
    *fin_host_ = FrameInputs<R>{};
    for (int k = 0; k < kReadback; ++k) readback_host_[k] = R(0);
    configure(c);
  }

  ~CudaCloth() override {
    drop_graphs();
    cudaFree(state_); cudaFree(ball_); cudaFree(acc_); cudaFree(fin_dev_); cudaFree(nonfinite_);
    cudaFreeHost(fin_host_); cudaFreeHost(readback_host_);
    cudaStreamDestroy(stream_);
  }

  void configure(const Config& c) override {
    if (c.n != n_) throw std::invalid_argument("configure: n cannot change");
    p_ = Params<R>::from(c);
    kernel_ = kernel_table<R>()[c.effects & (kNumEffectSets - 1)];
    effects_ = compiled_effect_set(c);
    strain_sweeps_ = strain_sweeps(c);
    drop_graphs();
    reset_contact();
    alt_ = make_cuda_integrator<R>(c);  // velocity Verlet, implicit Euler (their own units)
  }
  unsigned compiled_effects() const override {
    return effects_;
  }
  bool state_finite() override { return readback_host_[30] == R(0); }
  bool ball_contact_on() override {
    BallAcc<R> a;
    CB_CUDA(cudaMemcpy(&a, acc_, sizeof(a), cudaMemcpyDeviceToHost));
    return (effects_ & BALL) != 0 && a.contact_on != 0;
  }
  void set_wind(const double* w) override { fin_host_->wind = {R(w[0]), R(w[1]), R(w[2])}; }

  void set_hips(const double* h) override {
    // Mapped pinned memory: the graph's first kernel reads it at every launch.
    for (int k = 0; k < 4; ++k) fin_host_->hips[k] = {R(h[3 * k]), R(h[3 * k + 1]), R(h[3 * k + 2])};
  }

  void set_state(const double* pos, const double* vel) override {
    std::vector<R> h(6 * size_t(N_));
    for (int q = 0; q < N_; ++q)
      for (int d = 0; d < 3; ++d) {
        h[size_t(d) * N_ + q] = R(pos[3 * q + d]);
        h[size_t(3 + d) * N_ + q] = R(vel[3 * q + d]);
      }
    CB_CUDA(cudaMemcpy(buf(cur_), h.data(), sizeof(R) * h.size(), cudaMemcpyHostToDevice));
    CB_CUDA(cudaMemset(nonfinite_, 0, sizeof(int)));
    if (alt_) alt_->invalidate();
    reset_contact();
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
    if (alt_) alt_->invalidate();
    reset_contact();
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
    if (alt_ && alt_->needs_prime(*fin_host_)) {  // outside the graphs: only when inputs changed
      load_inputs<R><<<1, 32, 0, stream_>>>(fin_mapped_, fin_dev_);
      alt_->prime(stream_, alt_view(), cur_);
      cur_ = 1 - cur_;
    }
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
    load_inputs<R><<<1, 32, 0, stream_>>>(fin_mapped_, fin_dev_);
    int b = start;
    const unsigned blocks = unsigned(std::min((N_ + kBlock - 1) / kBlock, max_blocks_));
    for (int s = 0; s < substeps; ++s) {
      if (alt_)
        alt_->substep(stream_, alt_view(), b, dt);
      else
        kernel_<<<blocks, kBlock, 0, stream_>>>(p_, dev(b), dev(1 - b), fin_dev_, ball_ + b,
                                               ball_ + (1 - b), acc_, nonfinite_, dt);
      b = 1 - b;
      // Strain limiting, in place in buffer b: each pass the rows, then the columns.
      DevBuf<R> d = dev(b);
      const unsigned line_blocks = unsigned((n_ + kBlock - 1) / kBlock);
      for (int k = 0; k < strain_sweeps_; ++k) {
        strain_kernel<R><<<line_blocks, kBlock, 0, stream_>>>(p_, d.pos, d.vel, n_, 1, R(1) / dt);
        strain_kernel<R><<<line_blocks, kBlock, 0, stream_>>>(p_, d.pos, d.vel, 1, n_, R(1) / dt);
      }
    }
    gather_corners<R><<<1, 32, 0, stream_>>>(n_, dev(b), ball_ + b, nonfinite_, readback_mapped_);
    CB_CUDA(cudaStreamEndCapture(stream_, &graph));
    cudaGraphExec_t exec;
    CB_CUDA(cudaGraphInstantiate(&exec, graph, 0));
    CB_CUDA(cudaGraphDestroy(graph));
    return exec;
  }

  CudaView<R> alt_view() const {
    const DevBuf<R> a = dev(0), b = dev(1);
    return {p_, max_blocks_, {a.pos, b.pos}, {a.vel, b.vel}, ball_, fin_dev_, nonfinite_};
  }

  // Contact on until a substep shows that no node can reach the ball (forces.hpp).
  void reset_contact() {
    const BallAcc<R> a = BallAcc<R>::initial(strain_sweeps_ > 0);
    CB_CUDA(cudaMemcpy(acc_, &a, sizeof(a), cudaMemcpyHostToDevice));
  }

  void drop_graphs() {
    for (auto& kv : graphs_)
      if (kv.second) cudaGraphExecDestroy(kv.second);
    graphs_.clear();
  }

  void refresh_readback() {
    gather_corners<R><<<1, 32, 0, stream_>>>(n_, dev(cur_), ball_ + cur_, nonfinite_,
                                              readback_mapped_);
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
  FrameInputs<R>* fin_dev_ = nullptr;
  FrameInputs<R>* fin_host_ = nullptr;
  FrameInputs<R>* fin_mapped_ = nullptr;  // device view of fin_host_
  int* nonfinite_ = nullptr;
  unsigned effects_ = 0;
  int strain_sweeps_ = 0;
  R* readback_host_ = nullptr;
  R* readback_mapped_ = nullptr;  // device view of readback_host_
  int max_blocks_ = 1;
  int cur_ = 0;
  using GraphKey = std::tuple<int, R, int>;
  std::map<GraphKey, cudaGraphExec_t> graphs_;
  std::unique_ptr<CudaIntegrator<R>> alt_;  // null: semi-implicit Euler (se_substep)
};

}  // namespace

template <>
std::unique_ptr<Backend> make_cuda_backend_t<CB_REAL>(const Config& c) {
  return std::make_unique<CudaCloth<CB_REAL>>(c);
}

}  // namespace cb
