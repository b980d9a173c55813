// Compiled once per real type: CB_REAL is float or double (see native/CMakeLists.txt).
// CUDA backend: the shared core as one kernel per substep, the substeps of a frame captured
// in a CUDA graph. Per frame only the 4 corners and the ball are copied back; the mesh is
// copied only when asked for. This file never includes pybind11.
#include <cuda_runtime.h>

#include <algorithm>
#include <cstdlib>
#include <limits>
#include <cstdio>
#include <cstring>
#include <map>
#include <tuple>
#include <stdexcept>
#include <string>
#include <vector>

#include "core/backend.hpp"
#include "cuda/check.hpp"
#include "core/forces.hpp"
#include "cuda/integrators.hpp"
#include "cuda/reduce.cuh"

namespace cb {
namespace {

using ci::kBlock;
using ci::warp_sum;

// Per-frame readback: 4 corners (position, velocity), the ball (position, velocity), a flag.
constexpr int kReadback = 4 * 6 + 6 + 1;  // + the non-finite flag

template <class R>
struct DevBuf {
  Planes<R> pos, vel;
};

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

// The ball at the start of a substep, and whether that substep computes contact.
template <class R>
struct BallNow {
  Ball<R> b;
  bool contact;
};

// The ball's update for the previous substep, deferred to here (eqs. 5-6): every block of a
// substep computes it alike from the previous substep's finished sums, so no block waits
// for the others inside a launch (no last-block ticket); the launch boundary is the barrier.
// `prev` null: the first substep of a frame, whose ball the last frame finished.
template <class R, unsigned E>
__device__ BallNow<R> ball_now(const Params<R>& p, const Ball<R>* prev, const BallAcc<R>* acc,
                               const Ball<R>* cur, const BallCtl* ctl, R dt) {
  if (prev == nullptr) return {*cur, ctl->contact_on != 0};
  const Ball<R> b0 = *prev;
  const V3<R> sum{acc->f[0], acc->f[1], acc->f[2]};
  const Ball<R> b = ball_update<R, E>(p, b0, sum, dt);
  return {b, contact_possible(p, RealBits<R>::real(acc->nearest2), b.p - b0.p,
                              ctl->strain_limited != 0)};
}

// Programmatic dependent launch (Hopper): a launch made programmatic (`launch` below) may
// start while the one before it still runs, hiding its launch latency, and waits here
// until that one's writes are visible. For any other launch both are no-ops.
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

// One semi-implicit Euler substep for every node. With the ball on, each thread first
// brings the ball up to this substep (ball_now; at large n a launch of its own did), then
// each warp adds its nodes' contact forces and nearest distance to this substep's sums
// (`acc`), which the next launch reads; block 0 stores the ball and clears the sums the
// launch after next will use (`acc_next`).
template <class R, unsigned E>
__global__ void __launch_bounds__(kBlock) se_substep(Params<R> p, DevBuf<R> in, DevBuf<R> out,
                                                     const FrameInputs<R>* __restrict__ fin,
                                                     SubstepBall<R> sb, int* nonfinite, R dt) {
  follow_previous_launch();
  const int n = p.n;
  const int first = blockIdx.x * blockDim.x + threadIdx.x;
  V3<R> contact{R(0), R(0), R(0)};
  V3<R> ball_p{R(0), R(0), R(0)};
  bool touch = false;
  if constexpr ((E & BALL) != 0) {
    const BallNow<R> now = ball_now<R, E>(p, sb.prev, sb.acc_prev, sb.cur, sb.ctl, dt);
    ball_p = now.b.p;
    touch = now.contact;
    if (blockIdx.x == 0 && threadIdx.x == 0) {
      if (sb.prev != nullptr) *sb.cur = now.b;
      *sb.acc_next = BallAcc<R>::zero(p);
    }
  }
  // A grid-stride loop over the resident blocks (each thread then pays the ball's update
  // once), or one node a thread for the largest cloths (see capture).
  R check = 0;
  // While no node can touch the ball the sweep runs compiled without contact (the same
  // decision for the whole grid), still tracking the node nearest the ball.
  R near2 = std::numeric_limits<R>::infinity();
  for (int q = first; q < n * n; q += gridDim.x * blockDim.x) {
    const int i = q / n, j = q - i * n;
    if constexpr ((E & BALL) != 0) {
      V3<R> x;
      if (touch)
        contact += se_node_update<R, E>(p, in.pos, in.vel, out.pos, out.vel, *fin, ball_p, i, j,
                                        dt, check, &x);
      else
        se_node_update<R, (E & ~BALL)>(p, in.pos, in.vel, out.pos, out.vel, *fin, ball_p, i, j,
                                       dt, check, &x);
      const V3<R> d = x - ball_p;
      near2 = fmin(near2, dot(d, d));
    } else {
      contact += se_node_update<R, E>(p, in.pos, in.vel, out.pos, out.vel, *fin, ball_p, i, j,
                                      dt, check);
    }
  }
  if (check != R(0)) *nonfinite = 1;  // sticky until the host resets the state
  if constexpr ((E & BALL) == 0) {
    if (first == 0) *sb.next = *sb.cur;  // no ball in this scene: carry its state unchanged
  }
  if constexpr ((E & BALL) != 0) {
    // Each warp adds to the sums directly: only the few warps at the ball have anything to
    // add, and the others skip the shuffles too (whole warps reach here: the loop exits
    // per lane, but every lane of a launched warp arrives).
    const unsigned all = 0xffffffffu;
    const bool lead = (threadIdx.x & 31) == 0;
    if (__any_sync(all, contact.x != R(0) || contact.y != R(0) || contact.z != R(0))) {
      const R c[3] = {warp_sum(contact.x), warp_sum(contact.y), warp_sum(contact.z)};
      if (lead)
        for (int k = 0; k < 3; ++k) atomicAdd(&sb.acc->f[k], c[k]);
    }
    if (__any_sync(all, near2 < near_cutoff2(p))) {
      near2 = warp_min(near2);
      if (lead) atomicMin(&sb.acc->nearest2, RealBits<R>::of(near2));
    }
  }
}

// The end of a frame: the last substep's deferred ball update (when `sb.prev` is set),
// then the corners, the ball and the non-finite flag to the mapped read-back. With no
// read-back (`out` null) it is the ball's own launch before a substep (large n).
template <class R, unsigned E>
__global__ void finish_frame(Params<R> p, DevBuf<R> s, SubstepBall<R> sb, const int* nonfinite,
                             R dt, R* out) {
  follow_previous_launch();
  const int t = threadIdx.x;
  if (t < 4 && out != nullptr) {
    const int q = corner_node(t, p.n);
    V3<R> x = s.pos.get(q), v = s.vel.get(q);
    R* o = out + 6 * t;
    o[0] = x.x; o[1] = x.y; o[2] = x.z; o[3] = v.x; o[4] = v.y; o[5] = v.z;
  } else if (t == 4) {
    Ball<R> b = *sb.cur;
    if constexpr ((E & BALL) != 0) {
      if (sb.prev != nullptr) {
        const BallNow<R> now = ball_now<R, E>(p, sb.prev, sb.acc_prev, sb.cur, sb.ctl, dt);
        b = now.b;
        *sb.cur = b;
        sb.ctl->contact_on = now.contact ? 1 : 0;
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

template <class R>
__global__ void load_inputs(const FrameInputs<R>* host, FrameInputs<R>* dev) {
  follow_previous_launch();
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
                          SubstepBall<R>, int*, R);
template <class R>
using FinishFn = void (*)(Params<R>, DevBuf<R>, SubstepBall<R>, const int*, R, R*);

template <class R>
struct Kernels {
  KernelFn<R> substep;
  FinishFn<R> finish;
};

template <class R>
struct KernelEntry {
  template <unsigned E>
  struct At {
    // The frame's end needs only what the ball's update reads of the set.
    static constexpr Kernels<R> fn{&se_substep<R, E>, &finish_frame<R, E & (BALL | GRAVITY)>};
  };
};

template <class R>
const std::array<Kernels<R>, kNumEffectSets>& kernel_table() {
#ifdef CB_LAB_EFFECT_SET
  // A lab build (tools/lab/substep_bench.cu) compiles only the set it times, in seconds.
  static std::array<Kernels<R>, kNumEffectSets> t{};
  t[CB_LAB_EFFECT_SET] = KernelEntry<R>::template At<CB_LAB_EFFECT_SET>::fn;
  return t;
#else
  return dispatch_table<Kernels<R>, KernelEntry<R>::template At>();
#endif
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
    CB_CUDA(cudaMalloc(&ring_, sizeof(BallAcc<R>) * 3));
    CB_CUDA(cudaMalloc(&ctl_, sizeof(BallCtl)));
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
    sms_ = sms;
    max_blocks_ = sms * 8;
    int major = 0;
    CB_CUDA(cudaDeviceGetAttribute(&major, cudaDevAttrComputeCapabilityMajor, 0));
    // CLOTHBALL_CUDA_OVERLAP=0 turns overlapping launches off, to measure what they save.
    const char* overlap = std::getenv("CLOTHBALL_CUDA_OVERLAP");
    overlap_launches_ = major >= 9 && !(overlap && std::string(overlap) == "0");
    // CLOTHBALL_CUDA_NODE_A_THREAD=1 (or 0) takes the largest cloths' launch shape at every
    // size (or at none): the tests check it on small cloths against the oracle.
    const char* wide = std::getenv("CLOTHBALL_CUDA_NODE_A_THREAD");
    force_wide_ = wide ? std::string(wide) == "1" ? 1 : std::string(wide) == "0" ? 0 : -1 : -1;
    *fin_host_ = FrameInputs<R>{};
    for (int k = 0; k < kReadback; ++k) readback_host_[k] = R(0);
    configure(c);
  }

  ~CudaCloth() override {
    drop_graphs();
    cudaFree(state_); cudaFree(ball_); cudaFree(ring_); cudaFree(ctl_); cudaFree(fin_dev_); cudaFree(nonfinite_);
    cudaFreeHost(fin_host_); cudaFreeHost(readback_host_);
    cudaStreamDestroy(stream_);
  }

  void configure(const Config& c) override {
    if (c.n != n_) throw std::invalid_argument("configure: n cannot change");
    p_ = Params<R>::from(c);
    kernels_ = kernel_table<R>()[c.effects & (kNumEffectSets - 1)];
    int per_sm = 0;  // the substep kernel's blocks that one multiprocessor holds at once
    CB_CUDA(cudaOccupancyMaxActiveBlocksPerMultiprocessor(&per_sm, kernels_.substep, kBlock, 0));
    resident_blocks_ = std::max(1, per_sm) * sms_;
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
    BallCtl a;
    CB_CUDA(cudaMemcpy(&a, ctl_, sizeof(a), cudaMemcpyDeviceToHost));
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
    // A node a thread for the largest cloths, where a grid-stride loop leaves each thread's
    // loads waiting on its previous node's; the ball's update, which every block would
    // then repeat, becomes a launch of its own. The crossover was measured on an H100
    // (tools/lab/substep_bench.cu): the loop is faster up to n = 2048 (84.4 against 86.1
    // us), one node a thread at n = 4096 (333 against 414 us).
    const int node_blocks = (N_ + kBlock - 1) / kBlock;
    const bool wide = force_wide_ >= 0 ? force_wide_ == 1 : node_blocks > 64 * resident_blocks_;
    const bool ball_launch = wide && (effects_ & BALL) != 0;
    const unsigned blocks = unsigned(wide ? node_blocks : std::min(node_blocks, resident_blocks_));
    for (int s = 0; s < substeps; ++s) {
      if (alt_) {
        alt_->substep(stream_, alt_view(), b, dt);
      } else {
        SubstepBall<R> sb = substep_ball(s, b);
        if (ball_launch && sb.prev != nullptr) {
          launch(kernels_.finish, 1, 32, p_, dev(b), sb, static_cast<const int*>(nonfinite_), dt,
                 static_cast<R*>(nullptr));
          sb.prev = nullptr;  // the substep reads the updated ball
        }
        launch(kernels_.substep, blocks, kBlock, p_, dev(b), dev(1 - b),
               static_cast<const FrameInputs<R>*>(fin_dev_), sb, nonfinite_, dt);
      }
      b = 1 - b;
      // Strain limiting, in place in buffer b: each pass the rows, then the columns.
      DevBuf<R> d = dev(b);
      const unsigned line_blocks = unsigned((n_ + kBlock - 1) / kBlock);
      for (int k = 0; k < strain_sweeps_; ++k) {
        strain_kernel<R><<<line_blocks, kBlock, 0, stream_>>>(p_, d.pos, d.vel, n_, 1, R(1) / dt);
        strain_kernel<R><<<line_blocks, kBlock, 0, stream_>>>(p_, d.pos, d.vel, 1, n_, R(1) / dt);
      }
    }
    // The last substep's ball update is still due (semi-implicit Euler with the ball).
    const bool due = !alt_ && (effects_ & BALL) != 0;
    launch(kernels_.finish, 1, 32, p_, dev(b), due ? substep_ball(substeps, b) : substep_ball(0, b),
           static_cast<const int*>(nonfinite_), dt, readback_mapped_);
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

  // A launch into the frame's graph that may overlap the one before it (see
  // follow_previous_launch); an ordinary launch where that is off.
  template <class... Ps, class... As>
  void launch(void (*kernel)(Ps...), unsigned grid, unsigned block, As&&... args) {
    cudaLaunchConfig_t cfg{};
    cfg.gridDim = dim3(grid);
    cfg.blockDim = dim3(block);
    cfg.stream = stream_;
    cudaLaunchAttribute overlap{};
    overlap.id = cudaLaunchAttributeProgrammaticStreamSerialization;
    overlap.val.programmaticStreamSerializationAllowed = 1;
    cfg.attrs = &overlap;
    cfg.numAttrs = overlap_launches_ ? 1 : 0;
    CB_CUDA(cudaLaunchKernelEx(&cfg, kernel, std::forward<As>(args)...));
  }

  // Substep k of a frame that reads state buffer b (k = substeps: the frame's end).
  SubstepBall<R> substep_ball(int k, int b) const {
    Ball<R>* cur = ball_ + b;
    Ball<R>* other = ball_ + (1 - b);
    return {k == 0 ? nullptr : other, ring_ + (k + 2) % 3, cur, other,
            ring_ + k % 3, ring_ + (k + 1) % 3, ring_, ctl_};
  }

  // Contact on until a substep shows that no node can reach the ball (forces.hpp).
  void reset_contact() {
    const BallCtl c{1, strain_sweeps_ > 0 ? 1 : 0};
    CB_CUDA(cudaMemcpy(ctl_, &c, sizeof(c), cudaMemcpyHostToDevice));
    const BallAcc<R> z = BallAcc<R>::zero(p_);
    const BallAcc<R> ring[3] = {z, z, z};
    CB_CUDA(cudaMemcpy(ring_, ring, sizeof(ring), cudaMemcpyHostToDevice));
  }

  void drop_graphs() {
    for (auto& kv : graphs_)
      if (kv.second) cudaGraphExecDestroy(kv.second);
    graphs_.clear();
  }

  void refresh_readback() {
    kernels_.finish<<<1, 32, 0, stream_>>>(p_, dev(cur_), substep_ball(0, cur_), nonfinite_,
                                           R(0), readback_mapped_);
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
  Kernels<R> kernels_{};
  cudaStream_t stream_ = nullptr;
  R* state_ = nullptr;  // two buffers of 6 planes: x y z vx vy vz
  Ball<R>* ball_ = nullptr;
  BallAcc<R>* ring_ = nullptr;  // three substeps' ball sums (SubstepBall)
  BallCtl* ctl_ = nullptr;
  FrameInputs<R>* fin_dev_ = nullptr;
  FrameInputs<R>* fin_host_ = nullptr;
  FrameInputs<R>* fin_mapped_ = nullptr;  // device view of fin_host_
  int* nonfinite_ = nullptr;
  unsigned effects_ = 0;
  int strain_sweeps_ = 0;
  R* readback_host_ = nullptr;
  R* readback_mapped_ = nullptr;  // device view of readback_host_
  int max_blocks_ = 1;       // the other integrators' grids
  int sms_ = 1;
  int resident_blocks_ = 1;  // the substep kernel's grid: as many blocks as fit at once
  bool overlap_launches_ = false;  // programmatic dependent launch (compute capability >= 9)
  int force_wide_ = -1;            // CLOTHBALL_CUDA_NODE_A_THREAD: 1 always, 0 never, -1 auto
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
