// Linearised implicit Euler on the CUDA backend (see core/integrators.hpp). A substep is a
// right-hand-side kernel (specialised on the effect set), CG iterations of two kernels each
// (the operator, specialised on the stiffness effects only, and the node-local update), and
// a finishing kernel, all captured into the frame's graph. CG's scalars stay on the device:
// block sums plus atomics, the last block acting on the totals.
//
// The iterations are the body of a conditional WHILE node (CUDA >= 12.4): the update's last
// block counts the iteration and, when CG has converged or reached cg_max_iterations, ends
// the loop on the device, so a substep costs the iterations it uses (rounded up to the
// iterations in one turn of the loop, cg_unroll). With an older toolkit
// all cg_max_iterations pairs are captured and those after convergence return at once
// (they read the same scalars), which still costs their launches.
// Compiled once per real type (CB_REAL).
#include <algorithm>
#include <cstdlib>
#include <stdexcept>
#include <utility>

#include "core/backend.hpp"
#include "core/integrators.hpp"
#include "cuda/check.hpp"
#include "cuda/integrators.hpp"
#include "cuda/reduce.cuh"

// -DCB_CG_WHILE=0 forces the captured loop (to measure against it).
#ifndef CB_CG_WHILE
#if CUDART_VERSION >= 12040
#define CB_CG_WHILE 1
#else
#define CB_CG_WHILE 0
#endif
#endif
#if CB_CG_WHILE
#if CUDART_VERSION >= 13000  // the edge-data signatures lost their suffixes in 13.0
#define CB_CAPTURE_INFO cudaStreamGetCaptureInfo
#define CB_GRAPH_ADD_NODE cudaGraphAddNode
#define CB_UPDATE_CAPTURE_DEPS cudaStreamUpdateCaptureDependencies
#else
#define CB_CAPTURE_INFO cudaStreamGetCaptureInfo_v3
#define CB_GRAPH_ADD_NODE cudaGraphAddNode_v2
#define CB_UPDATE_CAPTURE_DEPS cudaStreamUpdateCaptureDependencies_v2
#endif
#elif CUDART_VERSION < 12030
using cudaGraphConditionalHandle = unsigned long long;  // unused without conditional nodes
#endif

namespace cb {
namespace {

using R = CB_REAL;
using ci::kBlock;

// CG scalars: sc[0] = |rhs|^2, then for each iteration k the triple (r.z, r.r, p.Ap) at
// sc[1 + 3k] (r.z and r.r of iterate k, p.Ap of iteration k). Zeroed before each substep.
struct IeArgs {
  Params<R> p;
  CgVectors<R> cg;
  R* sc;
  R* acc;  // 11 sums for the last-block patterns
  unsigned* ticket;
  unsigned* iter;     // the device-side loop's iteration count, then the update's ticket
  int max_iter;
  R tol, a_node, a_ball, dt;
};
__device__ __forceinline__ R* slot(const IeArgs& a, int k) { return a.sc + 1 + 3 * k; }

template <unsigned E>
__global__ void __launch_bounds__(kBlock)
    ie_rhs_kernel(IeArgs a, Planes<R> P, Planes<R> V, const FrameInputs<R>* __restrict__ fin,
                  const Ball<R>* __restrict__ ball) {
  const int n = a.p.n, N = n * n;
  const Ball<R> b = *ball;
  RhsSums<R> mine{};
  for (int q = blockIdx.x * blockDim.x + threadIdx.x; q < N; q += gridDim.x * blockDim.x) {
    const int i = q / n, j = q - i * n;
    ie_rhs_node<R, E>(a.p, P, V, a.cg, *fin, b.p, b.v, i, j, a.a_node, a.dt, mine);
  }
  const R v[11] = {mine.contact.x, mine.contact.y, mine.contact.z, mine.cj.x, mine.cj.y,
                   mine.cj.z, mine.cd.x, mine.cd.y, mine.cd.z, mine.bb, mine.rz};
  if (ci::grid_sum(v, a.acc, a.ticket)) {
    R t[11];
    for (int k = 0; k < 11; ++k) t[k] = ci::acc_read(a.acc, k);
    RhsSums<R> all{{t[0], t[1], t[2]}, {t[3], t[4], t[5]}, {t[6], t[7], t[8]}, R(0), R(0)};
    R bb = R(0), rz = R(0);
    ie_rhs_ball<R, E>(a.p, a.cg, b, all, a.a_ball, a.dt, N, bb, rz);
    a.sc[0] = t[9] + bb;
    slot(a, 0)[0] = t[10] + rz;
    for (int k = 0; k < 11; ++k) a.acc[k] = R(0);
    *a.ticket = 0;
    a.iter[0] = 0;
  }
}

template <unsigned S>
__device__ __forceinline__ void ie_apply(const IeArgs& a, Planes<R> P,
                                         const Ball<R>* __restrict__ ball, int k) {
  const R* s = slot(a, k);
  // Uniform. k reaches max_iter only in the loop's unrolled body, after the loop ended.
  if (k >= a.max_iter || cg_stopped(k, a.sc[0], k > 0 ? s[-1] : R(0), s[1], a.tol)) return;
  const int n = a.p.n, N = n * n, from = k & 1;
  const bool first = k == 0;
  const R beta = first ? R(0) : s[0] / s[-3];
  const V3<R> wb = cg_direction(a.cg, from, N, first, beta);
  V3<R> ball_p{R(0), R(0), R(0)}, cj_sum{R(0), R(0), R(0)};
  if constexpr ((S & BALL) != 0) ball_p = ball->p;
  R pap = R(0);
  for (int q = blockIdx.x * blockDim.x + threadIdx.x; q < N; q += gridDim.x * blockDim.x) {
    const int i = q / n, j = q - i * n;
    V3<R> cj{R(0), R(0), R(0)};
    pap += ie_apply_node<R, S>(a.p, P, a.cg, from, first, beta, ball_p, wb, i, j, a.a_node, a.dt,
                               cj);
    cj_sum += cj;
  }
  const R v[4] = {cj_sum.x, cj_sum.y, cj_sum.z, pap};
  if (ci::grid_sum(v, a.acc, a.ticket)) {
    const V3<R> cs{ci::acc_read(a.acc, 0), ci::acc_read(a.acc, 1), ci::acc_read(a.acc, 2)};
    const R pb = ie_apply_ball(a.cg, from, first, beta, cs, a.a_ball, a.dt, N);
    slot(a, k)[2] = ci::acc_read(a.acc, 3) + pb;
    for (int c = 0; c < 4; ++c) a.acc[c] = R(0);
    *a.ticket = 0;
  }
}

#if CB_CG_WHILE
// Iteration k read from the device (the body of the WHILE node).
template <unsigned S>
__global__ void __launch_bounds__(kBlock)
    ie_apply_kernel(IeArgs a, Planes<R> P, const Ball<R>* __restrict__ ball) {
  ie_apply<S>(a, P, ball, int(a.iter[0]));
}
#else
// Iteration k given at capture (all iterations captured).
template <unsigned S>
__global__ void __launch_bounds__(kBlock)
    ie_apply_kernel(IeArgs a, Planes<R> P, const Ball<R>* __restrict__ ball, int k) {
  ie_apply<S>(a, P, ball, k);
}
#endif

// x += alpha p, r -= alpha A p, z = M^-1 r, and the sums r . z, r . r of iterate k + 1. In
// the loop (`loop`) the last block also advances the count and ends the loop through
// `cond` once CG stops before iteration k + 1 (the same test as ie_apply's).
__device__ __forceinline__ void ie_update(const IeArgs& a, int N, int k, bool loop,
                                          cudaGraphConditionalHandle cond) {
  const R* s = slot(a, k);
  const R pap = s[2];
  if (!(pap > R(0))) {  // iteration k stopped (or found p . A p <= 0): uniform
#if CB_CG_WHILE
    // The count goes to max_iter so that the body's remaining kernels return at once.
    if (loop && blockIdx.x == 0 && threadIdx.x == 0) {
      a.iter[0] = unsigned(a.max_iter);
      cudaGraphSetConditional(cond, 0);
    }
#endif
    return;
  }
  const R alpha = s[0] / pap;
  R sums[2] = {R(0), R(0)};  // r . z, r . r of iterate k + 1
  for (int q = blockIdx.x * blockDim.x + threadIdx.x; q <= N; q += gridDim.x * blockDim.x)
    ie_update_entry(a.cg, 1 - (k & 1), q, alpha, sums[1], sums[0]);
  if (ci::grid_sum(sums, slot(a, k + 1), loop ? a.iter + 1 : static_cast<unsigned*>(nullptr))) {
    a.iter[1] = 0;
    a.iter[0] = unsigned(k + 1);
#if CB_CG_WHILE
    const R rr = ci::acc_read(slot(a, k + 1), 1);
    if (k + 1 >= a.max_iter || cg_stopped(k + 1, a.sc[0], pap, rr, a.tol)) {
      a.iter[0] = unsigned(a.max_iter);
      cudaGraphSetConditional(cond, 0);
    }
#endif
  }
}

#if CB_CG_WHILE
__global__ void __launch_bounds__(kBlock)
    ie_update_loop_kernel(IeArgs a, int N, cudaGraphConditionalHandle cond) {
  ie_update(a, N, int(a.iter[0]), true, cond);
}
#else
__global__ void __launch_bounds__(kBlock) ie_update_kernel(IeArgs a, int N, int k) {
  ie_update(a, N, k, false, cudaGraphConditionalHandle{});
}
#endif

__global__ void __launch_bounds__(kBlock)
    ie_finish_kernel(IeArgs a, Planes<R> P, Planes<R> V, Planes<R> P2, Planes<R> V2,
                     const Ball<R>* __restrict__ ball_in, Ball<R>* __restrict__ ball_out,
                     int* nonfinite, bool has_ball) {
  const int N = a.p.n * a.p.n;
  const int first = blockIdx.x * blockDim.x + threadIdx.x;
  R check = 0;
  for (int q = first; q < N; q += gridDim.x * blockDim.x)
    ie_finish_node(a.cg, P, V, P2, V2, q, a.dt, check);
  if (check != R(0)) *nonfinite = 1;
  if (first == 0) *ball_out = has_ball ? ie_finish_ball(a.cg, *ball_in, N, a.dt) : *ball_in;
}

using RhsKernel = void (*)(IeArgs, Planes<R>, Planes<R>, const FrameInputs<R>*, const Ball<R>*);
#if CB_CG_WHILE
using ApplyKernel = void (*)(IeArgs, Planes<R>, const Ball<R>*);
#else
using ApplyKernel = void (*)(IeArgs, Planes<R>, const Ball<R>*, int);
#endif
template <unsigned E>
struct RhsEntry {
  static constexpr RhsKernel fn = &ie_rhs_kernel<E>;
};
template <unsigned I>
struct ApplyEntry {
  static constexpr ApplyKernel fn = &ie_apply_kernel<stiff_set(I)>;
};


// CG iterations captured in each turn of the WHILE loop: CLOTHBALL_CG_UNROLL (1-32), to
// measure the trade between the loop's per-turn cost and the pairs run after CG stopped.
constexpr int kCgUnroll = 4;
int cg_unroll() {
  const char* env = std::getenv("CLOTHBALL_CG_UNROLL");
  const int u = env ? std::atoi(env) : kCgUnroll;
  return std::clamp(u, 1, 32);
}

class CudaImplicit final : public CudaIntegrator<R> {
 public:
  explicit CudaImplicit(const Config& c)
      : N_(c.n * c.n), effects_(c.effects & (kNumEffectSets - 1)),
        max_iter_(std::max(0, c.cg_max_iterations)), m_(c.node_mass),
        c_((c.effects & DAMPING) ? c.damping : 0.0), mb_((c.effects & BALL) ? c.ball_mass : 1.0),
        cb_((c.effects & BALL) ? c.ball_damping : 0.0),
        rhs_(dispatch_table<RhsKernel, RhsEntry>()[effects_]),
        apply_(dispatch_table<ApplyKernel, ApplyEntry, kNumStiffSets>()[stiff_index(effects_)]) {
    const size_t entries = size_t(N_) + 1;  // the nodes, then the ball
    CB_CUDA(cudaMalloc(&vec_, sizeof(R) * 21 * entries));
    CB_CUDA(cudaMemset(vec_, 0, sizeof(R) * 21 * entries));
    sc_count_ = 1 + 3 * (size_t(max_iter_) + 1);
    CB_CUDA(cudaMalloc(&sc_, sizeof(R) * (sc_count_ + 12)));
    CB_CUDA(cudaMemset(sc_, 0, sizeof(R) * (sc_count_ + 12)));
    CB_CUDA(cudaMalloc(&iter_, sizeof(unsigned) * 2));
    CB_CUDA(cudaMemset(iter_, 0, sizeof(unsigned) * 2));
    auto planes = [&](int k) {
      R* b = vec_ + size_t(3 * k) * entries;
      return Planes<R>{b, b + entries, b + 2 * entries};
    };
    args_.p = Params<R>::from(c);
    args_.cg = {planes(0), planes(1), planes(2), planes(3), {planes(4), planes(5)}, planes(6)};
    args_.sc = sc_;
    args_.acc = sc_ + sc_count_;
    args_.ticket = reinterpret_cast<unsigned*>(sc_ + sc_count_ + 11);
    args_.iter = iter_;
    args_.max_iter = max_iter_;
    args_.tol = R(c.cg_tolerance);
  }
  ~CudaImplicit() override {
    cudaFree(vec_);
    cudaFree(sc_);
    cudaFree(iter_);
  }

  void substep(cudaStream_t s, const CudaView<R>& v, int b, R dt) override {
    IeArgs a = args_;
    a.dt = dt;
    a.a_node = R(m_ + double(dt) * c_);
    a.a_ball = R(mb_ + double(dt) * cb_);
    const unsigned blocks = ci::grid_blocks(N_, v.max_blocks);
    CB_CUDA(cudaMemsetAsync(sc_, 0, sizeof(R) * sc_count_, s));
    const unsigned update_blocks = ci::grid_blocks(N_ + 1, v.max_blocks);
    rhs_<<<blocks, kBlock, 0, s>>>(a, v.pos[b], v.vel[b], v.fin, v.ball + b);
#if CB_CG_WHILE
    if (max_iter_ > 0) cg_loop(s, a, v.pos[b], v.ball + b, blocks, update_blocks);
#else
    for (int k = 0; k < max_iter_; ++k) {
      apply_<<<blocks, kBlock, 0, s>>>(a, v.pos[b], v.ball + b, k);
      ie_update_kernel<<<update_blocks, kBlock, 0, s>>>(a, N_, k);
    }
#endif
    ie_finish_kernel<<<blocks, kBlock, 0, s>>>(a, v.pos[b], v.vel[b], v.pos[1 - b],
                                              v.vel[1 - b], v.ball + b, v.ball + (1 - b),
                                              v.nonfinite, (effects_ & BALL) != 0);
  }

 private:
#if CB_CG_WHILE
  // Adds to the graph being captured on `s` a WHILE node whose body is one CG iteration (the
  // operator, then the update, whose last block ends the loop), and makes it what the
  // stream's next work depends on.
  void cg_loop(cudaStream_t s, const IeArgs& a, Planes<R> P, const Ball<R>* ball,
               unsigned blocks, unsigned update_blocks) {
    cudaStreamCaptureStatus status;
    cudaGraph_t graph;
    const cudaGraphNode_t* deps = nullptr;
    const cudaGraphEdgeData* edges = nullptr;
    size_t ndeps = 0;
    CB_CUDA(CB_CAPTURE_INFO(s, &status, nullptr, &graph, &deps, &edges, &ndeps));
    if (status != cudaStreamCaptureStatusActive)
      throw std::logic_error("implicit Euler's substep must be captured into a graph");
    cudaGraphConditionalHandle cond;
    // Reset to 1 at every launch of the frame's graph: the body runs at least once (its
    // first operator kernel returns at once where CG has nothing to do).
    CB_CUDA(cudaGraphConditionalHandleCreate(&cond, graph, 1, cudaGraphCondAssignDefault));
    cudaGraphNodeParams cp{};
    cp.type = cudaGraphNodeTypeConditional;
    cp.conditional.handle = cond;
    cp.conditional.type = cudaGraphCondTypeWhile;
    cp.conditional.size = 1;
    cudaGraphNode_t loop;
    CB_CUDA(CB_GRAPH_ADD_NODE(&loop, graph, deps, edges, ndeps, &cp));
    cudaGraph_t body = cp.conditional.phGraph_out[0];
    IeArgs args = a;
    int n = N_;
    void* apply_args[] = {&args, &P, &ball};
    void* update_args[] = {&args, &n, &cond};
    cudaKernelNodeParams kp{};
    kp.blockDim = dim3(kBlock);
    kp.func = reinterpret_cast<void*>(apply_);
    kp.gridDim = dim3(blocks);
    kp.kernelParams = apply_args;
    cudaKernelNodeParams up = kp;
    up.func = reinterpret_cast<void*>(&ie_update_loop_kernel);
    up.gridDim = dim3(update_blocks);
    up.kernelParams = update_args;
    // unroll_ iterations a body: each turn of the loop costs a device-side launch of the
    // body on top of its kernels; the pairs after CG stopped return at once.
    cudaGraphNode_t last = nullptr;
    for (int u = 0; u < unroll_; ++u) {
      cudaGraphNode_t apply_node, update_node;
      CB_CUDA(cudaGraphAddKernelNode(&apply_node, body, last ? &last : nullptr, last ? 1 : 0,
                                     &kp));
      CB_CUDA(cudaGraphAddKernelNode(&update_node, body, &apply_node, 1, &up));
      last = update_node;
    }
    CB_CUDA(CB_UPDATE_CAPTURE_DEPS(s, &loop, nullptr, 1, cudaStreamSetCaptureDependencies));
  }
#endif

  const int N_;
  const unsigned effects_;
  const int max_iter_;
  const int unroll_ = cg_unroll();  // CG iterations per turn of the device-side loop
  const double m_, c_, mb_, cb_;
  const RhsKernel rhs_;
  const ApplyKernel apply_;  // the operator kernel for the scene's stiffness effects
  R* vec_ = nullptr;  // the 7 CG vectors of N + 1 entries, 3 planes each
  R* sc_ = nullptr;   // CG scalars, then 11 sums and the ticket
  unsigned* iter_ = nullptr;  // IeArgs::iter
  size_t sc_count_ = 0;
  IeArgs args_{};
};

}  // namespace

template <>
std::unique_ptr<CudaIntegrator<CB_REAL>> make_cuda_implicit<CB_REAL>(const Config& c) {
  return std::make_unique<CudaImplicit>(c);
}

}  // namespace cb
