// Compiled once per real type: CB_REAL is float or double (see native/CMakeLists.txt).
// CUDA backend: the shared core as one kernel per substep, the substeps of a frame captured
// in a CUDA graph. Per frame only the 4 corners and the ball are copied back; the mesh is
// copied only when asked for. The kernels' bodies are cuda/substep.cuh's, which the batch's
// kernels (cuda/batch.cu) share; CudaBatch below steps many cloths with them, one graph a
// frame for all. This file never includes pybind11.
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
#include "core/batch_stepper.hpp"
#include "cuda/check.hpp"
#include "core/forces.hpp"
#include "cuda/integrators.hpp"
#include "cuda/reduce.cuh"
#include "cuda/substep.cuh"

namespace cb {
namespace {

using ci::kBlock;

// One semi-implicit Euler substep for every node of the cloth (se_substep_body).
template <class R, unsigned E>
__global__ void __launch_bounds__(kBlock) se_substep(Params<R> p, DevBuf<R> in, DevBuf<R> out,
                                                     const FrameInputs<R>* __restrict__ fin,
                                                     SubstepBall<R> sb, int* nonfinite, R dt) {
  follow_previous_launch();
  se_substep_body<R, E>(p, in, out, fin, sb, nonfinite, dt, int(blockIdx.x), int(gridDim.x));
}

// The end of a frame (finish_body), or with no read-back (`out` null) the ball's own launch
// before a substep (large n).
template <class R, unsigned E>
__global__ void finish_frame(Params<R> p, DevBuf<R> s, SubstepBall<R> sb, const int* nonfinite,
                             R dt, R* out) {
  follow_previous_launch();
  finish_body<R, E>(p, s, sb, nonfinite, dt, out, int(threadIdx.x));
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

// Several slots' node positions into one array, node-major (3 values a node, a slot after
// another): what a batch's mesh gather copies back in one transfer. src[k]: slot k's x
// plane, followed by its y and z planes (N values each).
template <class R>
__global__ void gather_positions_kernel(const R* const* __restrict__ src, int N, int m,
                                        R* __restrict__ out) {
  const size_t per = 3 * size_t(N), total = per * size_t(m);
  for (size_t i = size_t(blockIdx.x) * blockDim.x + threadIdx.x; i < total;
       i += size_t(gridDim.x) * blockDim.x) {
    const size_t k = i / per, r = i % per;
    out[i] = src[k][(r % 3) * size_t(N) + r / 3];
  }
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
    // The frame's end depends on the set only through the ball (gravity is run-time).
    static constexpr Kernels<R> fn{&se_substep<R, E>, &finish_frame<R, E & BALL>};
  };
};

template <class R>
const std::array<Kernels<R>, kNumEffectSets>& kernel_table() {
#ifdef CB_LAB_EFFECT_SET
  // A lab build (tools/lab/substep_bench.cu) compiles only the set it times, in seconds.
  static std::array<Kernels<R>, kNumEffectSets> t{};
  constexpr unsigned kLab = (CB_LAB_EFFECT_SET) & (kNumEffectSets - 1);  // its compiled bits
  t[kLab] = KernelEntry<R>::template At<kLab>::fn;
  return t;
#else
  return dispatch_table<Kernels<R>, KernelEntry<R>::template At>();
#endif
}

template <class R>
class CudaBatch;

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
    CB_CUDA(cudaHostAlloc(&fin_own_, sizeof(FrameInputs<R>), cudaHostAllocMapped));
    CB_CUDA(cudaHostAlloc(&readback_own_, sizeof(R) * kReadback, cudaHostAllocMapped));
    fin_host_ = fin_own_;
    readback_host_ = readback_own_;
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
    cudaFreeHost(fin_own_); cudaFreeHost(readback_own_);
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
    configure_tiled(c);
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
  DevBuf<R> dev(int b) const { return dev_buf(buf(b), N_); }

  // Capture one frame starting from buffer `start`: hips in, substeps, corners and ball out.
  cudaGraphExec_t capture(int start, int substeps, R dt) {
    CB_CUDA(cudaStreamBeginCapture(stream_, cudaStreamCaptureModeThreadLocal));
    load_inputs<R><<<1, 32, 0, stream_>>>(fin_mapped_, fin_dev_);
    int b = start;
    if (tiled_fn_ != nullptr) {  // the whole frame in one launch (cuda/tiled.cu)
      launch_tiled(start, substeps, dt);
      b = substeps % 2 ? 1 - start : start;
      launch(kernels_.finish, 1, 32, p_, dev(b), substep_ball(substeps, b),
             static_cast<const int*>(nonfinite_), dt, readback_mapped_);
      return instantiate();
    }
    // A node a thread for the largest cloths, where a grid-stride loop leaves each thread's
    // loads waiting on its previous node's; the ball's update, which every block would
    // then repeat, becomes a launch of its own. The crossover was measured on an H100
    // (tools/lab/substep_bench.cu): the loop is faster up to n = 2048 (84.4 against 86.1
    // us), one node a thread at n = 4096 (333 against 414 us).
    const int node_blocks = (N_ + kBlock - 1) / kBlock;
    const bool wide = node_a_thread();
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
    return instantiate();
  }

  // Ends the stream's capture (capture) and instantiates its graph.
  cudaGraphExec_t instantiate() {
    cudaGraph_t graph;
    CB_CUDA(cudaStreamEndCapture(stream_, &graph));
    cudaGraphExec_t exec;
    CB_CUDA(cudaGraphInstantiate(&exec, graph, 0));
    CB_CUDA(cudaGraphDestroy(graph));
    return exec;
  }

  // The tiled frame's plan and kernel where this configuration takes it (tiled_wanted:
  // it fits the device and n is large enough), else none.
  void configure_tiled(const Config& c) {
    tiled_fn_ = nullptr;
    int optin = 0;
    CB_CUDA(cudaDeviceGetAttribute(&optin, cudaDevAttrMaxSharedMemoryPerBlockOptin, 0));
    tiled_ = tiled_plan_for(c, sizeof(R), sms_, size_t(optin));
    const TiledFrameFn<R> fn = tiled_kernel_table<R>()[c.effects & (kNumEffectSets - 1)];
    if (fn == nullptr || !tiled_wanted(tiled_, c.n)) return;
    CB_CUDA(cudaFuncSetAttribute(fn, cudaFuncAttributeMaxDynamicSharedMemorySize,
                                 int(tiled_.shared_bytes)));
    int per_sm = 0;  // a cooperative launch needs every block resident at once
    CB_CUDA(cudaOccupancyMaxActiveBlocksPerMultiprocessor(&per_sm, fn, tiled_threads(sizeof(R)),
                                                          tiled_.shared_bytes));
    if (per_sm * sms_ >= tiled_.tiles()) tiled_fn_ = fn;
  }

  // The tiled frame from buffer `start`: one cooperative launch, a tile a block.
  void launch_tiled(int start, int substeps, R dt) {
    const TiledArgs<R> a{p_, tiled_.tiles_x, tiled_.th, tiled_.tw, tiled_.reach, state_, ball_,
                         ring_, ctl_, fin_dev_, nonfinite_, substeps, start, dt};
    cudaLaunchConfig_t cfg{};
    cfg.gridDim = dim3(unsigned(tiled_.tiles()));
    cfg.blockDim = dim3(unsigned(tiled_threads(sizeof(R))));
    cfg.dynamicSmemBytes = tiled_.shared_bytes;
    cfg.stream = stream_;
    cudaLaunchAttribute attr{};
    attr.id = cudaLaunchAttributeCooperative;
    attr.val.cooperative = 1;
    cfg.attrs = &attr;
    cfg.numAttrs = 1;
    CB_CUDA(cudaLaunchKernelEx(&cfg, tiled_fn_, a));
  }

  // (make_cuda_batch_stepper_t asks.)
 public:
  // How a frame is stepped (Backend::path).
  std::string path() const override {
    if (tiled_fn_ != nullptr) return "tiled";
    return !alt_ && node_a_thread() ? "node_a_thread" : "substeps";
  }

  bool node_a_thread() const {
    const int node_blocks = (N_ + kBlock - 1) / kBlock;
    return force_wide_ >= 0 ? force_wide_ == 1 : node_blocks > 64 * resident_blocks_;
  }

  // Whether CudaBatch steps this configuration: semi-implicit Euler without strain
  // limiting, at the sizes where a lone cloth's substep is one grid-stride launch. The
  // rest steps slot by slot, each slot's own graph: velocity Verlet and implicit Euler
  // (their own units, and a priming pass outside the graph), strain limiting (its line
  // passes), and the largest cloths (one node a thread, the ball's update a launch of its
  // own; one such slot fills the device by itself). CLOTHBALL_CUDA_BATCH=0 turns the
  // batched path off, to measure what it saves.
  bool batchable() const {
    const char* env = std::getenv("CLOTHBALL_CUDA_BATCH");
    if (env && std::string(env) == "0") return false;
    return !alt_ && strain_sweeps_ == 0 && !node_a_thread();
  }

 private:
  // The batch's view of this cloth, the current buffer first.
  SlotDev<R> slot_dev() const {
    return {{buf(cur_), buf(1 - cur_)}, {ball_ + cur_, ball_ + (1 - cur_)}, ring_, ctl_,
            fin_dev_, fin_mapped_, nonfinite_, readback_mapped_};
  }

  // Moves the mapped inputs and read-back to a batch's rows (host pointers and their
  // device views), with their current values; the graphs, which hold the old ones, go.
  void bind_io(FrameInputs<R>* fin, FrameInputs<R>* fin_mapped, R* rb, R* rb_mapped) {
    *fin = *fin_host_;
    std::copy(readback_host_, readback_host_ + kReadback, rb);
    fin_host_ = fin;
    fin_mapped_ = fin_mapped;
    readback_host_ = rb;
    readback_mapped_ = rb_mapped;
    drop_graphs();
  }

  CudaView<R> alt_view() const {
    const DevBuf<R> a = dev(0), b = dev(1);
    return {p_, max_blocks_, {a.pos, b.pos}, {a.vel, b.vel}, ball_, fin_dev_, nonfinite_};
  }

  // A launch into the frame's graph that may overlap the one before it.
  template <class... Ps, class... As>
  void launch(void (*kernel)(Ps...), unsigned grid, unsigned block, As&&... args) {
    launch_kernel(stream_, overlap_launches_, kernel, grid, block, std::forward<As>(args)...);
  }

  // Substep k of a frame that reads state buffer b (k = substeps: the frame's end).
  SubstepBall<R> substep_ball(int k, int b) const {
    return substep_ball_at(ball_ + b, ball_ + (1 - b), ring_, ctl_, k);
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
  FrameInputs<R>* fin_own_ = nullptr;      // this cloth's mapped inputs
  R* readback_own_ = nullptr;               // and read-back
  // The mapped inputs and read-back in use: this cloth's own, or in a batch its rows of
  // the batch's arrays (bind_io).
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
  TiledPlan tiled_{};                   // the tiled frame's layout (where it fits)
  TiledFrameFn<R> tiled_fn_ = nullptr;  // set: frames run tiled (configure_tiled)
  int cur_ = 0;
  using GraphKey = std::tuple<int, R, int>;
  std::map<GraphKey, cudaGraphExec_t> graphs_;
  std::unique_ptr<CudaIntegrator<R>> alt_;  // null: semi-implicit Euler (se_substep)

  friend class CudaBatch<R>;
};

// Every slot of a batch (cb::Batch) of CudaCloths of one configuration in one graph a
// frame: one launch copies all slots' hands and wind in from one mapped array, each
// substep is one launch over a group of slots (capture), running se_substep_body as the
// lone cloth does (blockIdx.x slot-major; a slot's blocks loop over its nodes, see
// slot_blocks, so each node's arithmetic is its lone cloth's), and one launch writes every
// slot's corners, ball and non-finite flag to one mapped read-back array; one
// synchronisation a frame for all. A slot's own calls keep working: its mapped inputs and
// read-back are its rows of those arrays (CudaCloth::bind_io). The table of slots, and so
// the graphs, are rebuilt only when the stepped set changes (slots added, removed,
// paused) or a slot's current buffer is not where the table has it.
template <class R>
class CudaBatch final : public BatchStepper {
 public:
  CudaBatch(const CudaCloth<R>& first, int capacity)
      : p_(first.p_),
        N_(first.N_),
        effects_(first.effects_),
        resident_blocks_(first.resident_blocks_),
        group_(group_size(first)),
        overlap_(first.overlap_launches_),
        kernels_(batch_kernel_table<R>()[first.effects_ & (kNumEffectSets - 1)]),
        fused_bytes_(fused_bytes(first.N_)),
        cloths_(size_t(capacity), nullptr) {
    const size_t cap = size_t(capacity);
    if (fused_bytes_ > 0) {
      CB_CUDA(cudaFuncSetAttribute(kernels_.frame, cudaFuncAttributeMaxDynamicSharedMemorySize,
                                   int(fused_bytes_)));
      fused_threads_ = fused_threads(kernels_.frame, N_, fused_bytes_);
    }
    if (blocking_wait())  // first: a bad value throws before anything is allocated
      CB_CUDA(cudaEventCreateWithFlags(&done_, cudaEventBlockingSync | cudaEventDisableTiming));
    CB_CUDA(cudaStreamCreateWithFlags(&stream_, cudaStreamNonBlocking));
    CB_CUDA(cudaMalloc(&table_, sizeof(SlotDev<R>) * cap));
    CB_CUDA(cudaHostAlloc(&fin_host_, sizeof(FrameInputs<R>) * cap, cudaHostAllocMapped));
    CB_CUDA(cudaHostAlloc(&readback_host_, sizeof(R) * kReadback * cap, cudaHostAllocMapped));
    CB_CUDA(cudaHostGetDevicePointer(&fin_mapped_, fin_host_, 0));
    CB_CUDA(cudaHostGetDevicePointer(&readback_mapped_, readback_host_, 0));
    std::fill(fin_host_, fin_host_ + cap, FrameInputs<R>{});
    std::fill(readback_host_, readback_host_ + kReadback * cap, R(0));
  }

  ~CudaBatch() override {
    drop_graphs();
    cudaFree(gather_src_);
    cudaFree(gather_dev_);
    cudaFreeHost(gather_host_);
    cudaFree(table_);
    cudaFreeHost(fin_host_);
    cudaFreeHost(readback_host_);
    if (done_ != nullptr) cudaEventDestroy(done_);
    cudaStreamDestroy(stream_);
  }

  void attach(int s, Backend& b) override {
    auto* c = dynamic_cast<CudaCloth<R>*>(&b);
    if (c == nullptr || c->N_ != N_ || c->effects_ != effects_)
      throw std::logic_error("CudaBatch: slot " + std::to_string(s) +
                             " is not a CUDA cloth of the batch's configuration");
    const size_t row = size_t(s);
    c->bind_io(fin_host_ + row, fin_mapped_ + row, readback_host_ + kReadback * row,
               readback_mapped_ + kReadback * row);
    cloths_.at(row) = c;
    dirty_ = true;
  }

  void detach(int s) override {
    cloths_.at(size_t(s)) = nullptr;
    dirty_ = true;
  }

  void step(const int* slots, int m, int frames, int substeps, double dt) override {
    if (frames <= 0 || m <= 0) return;
    if (!table_holds(slots, m)) build(slots, m);
    for (int f = 0; f < frames; ++f) {
      // As a lone cloth: one graph per (substeps, dt, buffer the table's slots start from).
      cudaGraphExec_t& g = graphs_[GraphKey{substeps, R(dt), flip_}];
      if (!g) g = capture(substeps, R(dt), flip_);
      CB_CUDA(cudaGraphLaunch(g, stream_));
      if (substeps % 2) flip_ = 1 - flip_;
    }
    wait();
    for (size_t k = 0; k < built_.size(); ++k)
      cloths_[size_t(built_[k])]->cur_ = built_cur_[k] ^ flip_;
  }

  // The meshes due at a frame: one kernel gathers the slots' current positions into one
  // device array and one copy brings it back (a copy a slot cost ~10 ms for 256 slots).
  bool gather_positions(const int* slots, int m, double* out) override {
    if (m <= 0) return true;
    const size_t per = 3 * size_t(N_), count = per * size_t(m);
    std::vector<const R*> src(static_cast<size_t>(m));
    for (int k = 0; k < m; ++k) {
      const CudaCloth<R>* c = cloths_.at(size_t(slots[k]));
      if (c == nullptr)
        throw std::logic_error("CudaBatch: slot " + std::to_string(slots[k]) + " is not attached");
      src[size_t(k)] = c->buf(c->cur_);
    }
    if (size_t(m) > gather_slots_) {  // grown to the most slots asked at once, then kept
      cudaFree(gather_src_);
      cudaFree(gather_dev_);
      cudaFreeHost(gather_host_);
      CB_CUDA(cudaMalloc(&gather_src_, sizeof(R*) * size_t(m)));
      CB_CUDA(cudaMalloc(&gather_dev_, sizeof(R) * count));
      CB_CUDA(cudaHostAlloc(&gather_host_, sizeof(R) * count, cudaHostAllocDefault));
      gather_slots_ = size_t(m);
    }
    CB_CUDA(cudaMemcpyAsync(gather_src_, src.data(), sizeof(R*) * src.size(),
                            cudaMemcpyHostToDevice, stream_));
    const unsigned blocks = unsigned(std::min<size_t>((count + kBlock - 1) / kBlock, 4096));
    gather_positions_kernel<R><<<blocks, kBlock, 0, stream_>>>(gather_src_, N_, m, gather_dev_);
    CB_CUDA(cudaGetLastError());
    CB_CUDA(cudaMemcpyAsync(gather_host_, gather_dev_, sizeof(R) * count,
                            cudaMemcpyDeviceToHost, stream_));
    wait();
    for (size_t i = 0; i < count; ++i) out[i] = double(gather_host_[i]);
    return true;
  }

 private:
  // Whether the device table describes exactly these slots, each at its current buffer.
  bool table_holds(const int* slots, int m) const {
    if (dirty_ || size_t(m) != built_.size()) return false;
    for (int k = 0; k < m; ++k) {
      if (slots[k] != built_[size_t(k)]) return false;
      const CudaCloth<R>* c = cloths_.at(size_t(slots[k]));
      if (c == nullptr || c->cur_ != (built_cur_[size_t(k)] ^ flip_)) return false;
    }
    return true;
  }

  void build(const int* slots, int m) {
    std::vector<SlotDev<R>> h(static_cast<size_t>(m));
    built_.assign(slots, slots + m);
    built_cur_.resize(size_t(m));
    for (int k = 0; k < m; ++k) {
      const CudaCloth<R>* c = cloths_.at(size_t(slots[k]));
      if (c == nullptr)
        throw std::logic_error("CudaBatch: slot " + std::to_string(slots[k]) + " is not attached");
      h[size_t(k)] = c->slot_dev();
      built_cur_[size_t(k)] = c->cur_;
    }
    CB_CUDA(cudaMemcpyAsync(table_, h.data(), sizeof(SlotDev<R>) * h.size(),
                            cudaMemcpyHostToDevice, stream_));
    CB_CUDA(cudaStreamSynchronize(stream_));
    drop_graphs();
    flip_ = 0;
    dirty_ = false;
  }

  // One frame for every slot of the table, each starting from its table buffer b0.
  // The substeps go group by group of slots (group_), each group through all of them
  // before the next: a group's two state buffers fit in L2, so its substeps after the
  // first read what the one before wrote from L2 rather than DRAM (all slots' states do
  // not fit: 173 KB a classic n = 60 slot in float32, 50 MB of L2 on an H100).
  cudaGraphExec_t capture(int substeps, R dt, int b0) {
    const int m = int(built_.size());
    const SlotDev<R>* t = table_;
    cudaGraph_t graph;
    CB_CUDA(cudaStreamBeginCapture(stream_, cudaStreamCaptureModeThreadLocal));
    launch_kernel(stream_, false, kernels_.load, unsigned((m + kBlock - 1) / kBlock),
                  unsigned(kBlock), t, m);
    if (fused_bytes_ > 0) {  // the whole frame in one launch, a block a slot
      launch_kernel_shared(stream_, overlap_, fused_bytes_, kernels_.frame, unsigned(m),
                           unsigned(fused_threads_), p_, t, substeps, b0, dt);
    } else {
      const int group = group_ > 0 ? group_ : m;
      for (int g0 = 0; g0 < m; g0 += group) {
        const int mg = std::min(group, m - g0);
        int b = b0;
        for (int k = 0; k < substeps; ++k) {
          const int blocks = slot_blocks(mg);
          launch_kernel(stream_, overlap_, kernels_.substep, unsigned(mg) * unsigned(blocks),
                        unsigned(kBlock), p_, t + g0, blocks, k, b, dt);
          b = 1 - b;
        }
      }
      const int b = substeps % 2 ? 1 - b0 : b0;
      launch_kernel(stream_, overlap_, kernels_.finish, unsigned(m), 32u, p_, t, substeps, b,
                    dt);
    }
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

  // How the stepping thread waits for the GPU (a frame, a mesh gather): by default the
  // runtime's stream synchronisation, which with one context on a many-core host spins a
  // core until the work is done (the native frame loop's thread, a frame a millisecond);
  // CLOTHBALL_CUDA_WAIT=block waits on a blocking-sync event instead: the thread sleeps
  // until the GPU's interrupt, its CPU freed at the cost of that wake-up's latency.
  static bool blocking_wait() {
    const char* env = std::getenv("CLOTHBALL_CUDA_WAIT");
    if (env == nullptr || *env == '\0' || std::strcmp(env, "spin") == 0) return false;
    if (std::strcmp(env, "block") == 0) return true;
    throw std::invalid_argument(
        std::string("CLOTHBALL_CUDA_WAIT must be 'spin' or 'block', got '") + env + "'");
  }

  void wait() {
    if (done_ == nullptr) {
      CB_CUDA(cudaStreamSynchronize(stream_));
      return;
    }
    CB_CUDA(cudaEventRecord(done_, stream_));
    CB_CUDA(cudaEventSynchronize(done_));
  }

  // Slots whose two state buffers take half the L2 (the rest holds what else the substep
  // reads); CLOTHBALL_CUDA_BATCH_GROUP=k takes k (0: every slot in each launch), to measure.
  // A slot's blocks in a substep launch of `m` slots: a node a thread (the lone cloth's
  // grid) while the launch does not fill the device, else fewer blocks, down to about 5
  // nodes a thread (a grid-stride loop within the slot), which pays each thread's ball
  // update and table reads over several nodes. Measured on an H100
  // (tools/lab/batch_bench.cu, classic n = 60, frame p50): 1024 slots, three runs each:
  // 15 blocks a slot (a node a thread) 866-898 us, 8 blocks 773-851 us, 3 blocks 761-769
  // us; one slot: 3 blocks 61.5 us, 15 (this rule) 29.6 us, its own graph alone 27.8 us.
  int slot_blocks(int m) const {
    constexpr int kNodesPerThread = 5;
    const int node_blocks = (N_ + kBlock - 1) / kBlock;
    const int fewest = (N_ + kNodesPerThread * kBlock - 1) / (kNodesPerThread * kBlock);
    const int fill = (resident_blocks_ + m - 1) / m;  // blocks a slot for one full wave
    return std::max(1, std::min(std::min(node_blocks, resident_blocks_), std::max(fewest, fill)));
  }

  // Shared memory for a slot's two state buffers (12 planes of N) where they fit in one
  // block's and CLOTHBALL_CUDA_BATCH_FUSED is not 0 (to measure against the launches a
  // substep); 0: a launch a substep. On an H100 float32 fits up to n = 69.
  static size_t fused_bytes(int N) {
    const char* env = std::getenv("CLOTHBALL_CUDA_BATCH_FUSED");
    if (env && std::atoi(env) == 0) return 0;
    int dev = 0, optin = 0;
    CB_CUDA(cudaGetDevice(&dev));
    CB_CUDA(cudaDeviceGetAttribute(&optin, cudaDevAttrMaxSharedMemoryPerBlockOptin, dev));
    const size_t bytes = sizeof(R) * 12 * size_t(N);
    return bytes <= size_t(optin) ? bytes : 0;
  }

  // The fused frame's block: the fewest idle lanes in a substep's last round of nodes
  // (a slot's N nodes go in ceil(N / T) rounds of T threads) among the sizes that keep as
  // many threads on a multiprocessor as one block of kFusedBlock does (where a slot's
  // state leaves room for two blocks), so latency hiding is no worse. Default n = 48:
  // 2 304 nodes take 3 rounds of 1 024 (75 % of the lanes busy) or 5 of 512 (90 %), two
  // slots a multiprocessor, the one's barriers covered by the other's work.
  // CLOTHBALL_CUDA_FUSED_THREADS=T takes T (a multiple of 32 up to kFusedBlock), to measure.
  static int fused_threads(void (*frame)(Params<R>, const SlotDev<R>*, int, int, R), int N,
                           size_t bytes) {
    if (const char* env = std::getenv("CLOTHBALL_CUDA_FUSED_THREADS")) {
      const int t = std::atoi(env);
      if (t < 32 || t > kFusedBlock || t % 32 != 0)
        throw std::invalid_argument("CLOTHBALL_CUDA_FUSED_THREADS must be a multiple of 32 "
                                    "in 32..1024, got '" + std::string(env) + "'");
      return t;
    }
    int best = kFusedBlock;
    double best_busy = 0;
    for (int t = kFusedBlock; t >= 128; t /= 2) {
      int per_sm = 0;
      CB_CUDA(cudaOccupancyMaxActiveBlocksPerMultiprocessor(&per_sm, frame, t, bytes));
      if (per_sm * t < kFusedBlock) continue;
      const int rounds = (N + t - 1) / t;
      const double busy = double(N) / (double(rounds) * t);
      if (busy > best_busy + 1e-9) {
        best = t;
        best_busy = busy;
      }
    }
    return best;
  }

  static int group_size(const CudaCloth<R>& c) {
    const char* env = std::getenv("CLOTHBALL_CUDA_BATCH_GROUP");
    if (env) return std::max(0, std::atoi(env));
    int l2 = 0;
    CB_CUDA(cudaDeviceGetAttribute(&l2, cudaDevAttrL2CacheSize, 0));
    if (l2 <= 0) return 0;  // no L2 reported: nothing to keep a group in
    const size_t slot_bytes = sizeof(R) * 12 * size_t(c.N_);
    return int(std::max<size_t>(1, size_t(l2) / 2 / slot_bytes));
  }

  const Params<R> p_;
  const int N_;
  const unsigned effects_;
  const int resident_blocks_;  // substep blocks the device holds at once (CudaCloth's)
  const int group_;   // slots stepped through a frame's substeps together (0: all)
  const bool overlap_;
  const BatchKernels<R> kernels_;
  const size_t fused_bytes_;  // > 0: the frame in one launch (batch_frame), else a launch a substep
  int fused_threads_ = kFusedBlock;  // its block (fused_threads)
  std::vector<CudaCloth<R>*> cloths_;  // by slot; null: not attached
  cudaStream_t stream_ = nullptr;
  cudaEvent_t done_ = nullptr;  // CLOTHBALL_CUDA_WAIT=block: a frame's end (wait())
  SlotDev<R>* table_ = nullptr;        // the stepped slots (built_), on the device
  FrameInputs<R>* fin_host_ = nullptr;  // a row a slot, mapped
  FrameInputs<R>* fin_mapped_ = nullptr;
  R* readback_host_ = nullptr;          // kReadback values a slot, mapped
  R* readback_mapped_ = nullptr;
  const R** gather_src_ = nullptr;      // gather_positions: the slots' planes (device)
  R* gather_dev_ = nullptr;             // their positions, gathered
  R* gather_host_ = nullptr;            // and copied back (pinned)
  size_t gather_slots_ = 0;             // slots the gather buffers hold
  std::vector<int> built_;              // the slots in table_, in its order
  std::vector<int> built_cur_;          // each one's current buffer when the table was built
  int flip_ = 0;                        // table buffer the next frame starts from
  bool dirty_ = true;                   // a slot was attached or detached since build
  using GraphKey = std::tuple<int, R, int>;
  std::map<GraphKey, cudaGraphExec_t> graphs_;
};

}  // namespace

template <>
std::unique_ptr<Backend> make_cuda_backend_t<CB_REAL>(const Config& c) {
  return std::make_unique<CudaCloth<CB_REAL>>(c);
}

template <>
std::unique_ptr<BatchStepper> make_cuda_batch_stepper_t<CB_REAL>(Backend& first, int capacity) {
  auto* c = dynamic_cast<CudaCloth<CB_REAL>*>(&first);
  if (c == nullptr || !c->batchable()) return nullptr;
  return std::make_unique<CudaBatch<CB_REAL>>(*c, capacity);
}

}  // namespace cb
