// Velocity Verlet on the CUDA backend (see core/integrators.hpp): per substep a node-local
// drift kernel (not specialised) and one effect-specialised force-and-kick kernel whose
// last block kicks the ball. F is kept per node on the device between substeps and frames;
// a priming force pass (a kick with dt = 0) recomputes it before a frame whenever the
// state, the ball, the hands or the wind changed. Compiled once per real type (CB_REAL).
#include <cstring>
#include <stdexcept>
#include <utility>

#include "core/backend.hpp"
#include "core/integrators.hpp"
#include "cuda/check.hpp"
#include "cuda/integrators.hpp"
#include "cuda/reduce.cuh"

namespace cb {
namespace {

using R = CB_REAL;
using ci::kBlock;

__global__ void __launch_bounds__(kBlock)
    vv_drift_kernel(int n, int N, R inv_mass, R gamma, Planes<R> P, Planes<R> V, Planes<R> F,
                    Ball<R>* ball, const V3<R>* fb, R ball_inv_mass, R gamma_b, bool has_ball,
                    R dt) {
  const int first = blockIdx.x * blockDim.x + threadIdx.x;
  for (int q = first; q < N; q += gridDim.x * blockDim.x) {
    V3<R> x = P.get(q), u = V.get(q);
    vv_drift(x, u, F.get(q), node_inv_mass(inv_mass, n, q), gamma, dt);
    P.set(q, x);
    V.set(q, u);
  }
  if (has_ball && first == 0) {
    Ball<R> b = *ball;
    vv_drift(b.p, b.v, *fb, ball_inv_mass, gamma_b, dt);
    *ball = b;
  }
}

struct VvArgs {
  Params<R> p;
  Planes<R> F;
  V3<R>* fb;       // the ball's F
  R* acc;          // 3 contact sums
  unsigned* ticket;
  R gamma, gamma_b;
};

template <unsigned E>
__global__ void __launch_bounds__(kBlock)
    vv_force_kernel(VvArgs a, Planes<R> P, Planes<R> V, Planes<R> P2, Planes<R> V2,
                    const FrameInputs<R>* __restrict__ fin, const Ball<R>* __restrict__ ball_in,
                    Ball<R>* __restrict__ ball_out, int* nonfinite, R dt) {
  const Params<R>& p = a.p;
  const int n = p.n;
  V3<R> ball_p{R(0), R(0), R(0)}, contact{R(0), R(0), R(0)};
  if constexpr ((E & BALL) != 0) ball_p = ball_in->p;
  const int first = blockIdx.x * blockDim.x + threadIdx.x;
  R check = 0;
  for (int q = first; q < n * n; q += gridDim.x * blockDim.x) {
    const int i = q / n, j = q - i * n;
    contact += vv_force_node<R, E>(p, P, V, P2, V2, a.F, *fin, ball_p, i, j, a.gamma, dt, check);
  }
  if (check != R(0)) *nonfinite = 1;
  if constexpr ((E & BALL) == 0) {
    if (first == 0) *ball_out = *ball_in;
  } else {
    const R c[3] = {contact.x, contact.y, contact.z};
    if (ci::grid_sum(c, a.acc, a.ticket)) {
      const V3<R> sum{ci::acc_read(a.acc, 0), ci::acc_read(a.acc, 1), ci::acc_read(a.acc, 2)};
      const V3<R> fb = vv_ball_force<R>(p, sum);
      Ball<R> b = *ball_in;
      b.v = vv_kick(b.v, fb, p.ball_inv_mass, a.gamma_b, dt);
      *ball_out = b;
      *a.fb = fb;
      a.acc[0] = a.acc[1] = a.acc[2] = R(0);
      *a.ticket = 0;
    }
  }
}

using ForceKernel = void (*)(VvArgs, Planes<R>, Planes<R>, Planes<R>, Planes<R>,
                             const FrameInputs<R>*, const Ball<R>*, Ball<R>*, int*, R);
template <unsigned E>
struct ForceEntry {
  static constexpr ForceKernel fn = &vv_force_kernel<E>;
};

class CudaVerlet final : public CudaIntegrator<R> {
 public:
  explicit CudaVerlet(const Config& c)
      : N_(c.n * c.n), effects_(c.effects & (kNumEffectSets - 1)),
        force_(dispatch_table<ForceKernel, ForceEntry>()[effects_]) {
    CB_CUDA(cudaMalloc(&f_, sizeof(R) * 3 * size_t(N_)));
    CB_CUDA(cudaMemset(f_, 0, sizeof(R) * 3 * size_t(N_)));
    CB_CUDA(cudaMalloc(&fb_, sizeof(V3<R>)));
    CB_CUDA(cudaMemset(fb_, 0, sizeof(V3<R>)));
    CB_CUDA(cudaMalloc(&acc_, sizeof(R) * 4));
    CB_CUDA(cudaMemset(acc_, 0, sizeof(R) * 4));
    args_.p = vv_params(Params<R>::from(c));
    args_.F = {f_, f_ + N_, f_ + 2 * size_t(N_)};
    args_.fb = fb_;
    args_.acc = acc_;
    args_.ticket = reinterpret_cast<unsigned*>(acc_ + 3);
    args_.gamma = (c.effects & DAMPING) ? R(c.damping / c.node_mass) : R(0);
    args_.gamma_b = (c.effects & BALL) ? R(c.ball_damping / c.ball_mass) : R(0);
  }
  ~CudaVerlet() override {
    cudaFree(f_);
    cudaFree(fb_);
    cudaFree(acc_);
  }

  void substep(cudaStream_t s, const CudaView<R>& v, int b, R dt) override {
    const unsigned blocks = ci::grid_blocks(N_, v.max_blocks);
    vv_drift_kernel<<<blocks, kBlock, 0, s>>>(v.p.n, N_, v.p.inv_mass, args_.gamma, v.pos[b], v.vel[b],
                                              args_.F, v.ball + b, fb_, v.p.ball_inv_mass,
                                              args_.gamma_b, (effects_ & BALL) != 0, dt);
    force(s, v, b, dt);
  }
  bool needs_prime(const FrameInputs<R>& fin) override {
    // F depends on the hands (coupling) and the wind too.
    const bool need = !primed_ || std::memcmp(&fin, &fin_, sizeof fin_) != 0;
    fin_ = fin;
    return need;
  }
  void prime(cudaStream_t s, const CudaView<R>& v, int b) override {
    force(s, v, b, R(0));
    CB_CUDA(cudaGetLastError());
    primed_ = true;
  }
  void invalidate() override { primed_ = false; }

 private:
  void force(cudaStream_t s, const CudaView<R>& v, int b, R dt) {
    force_<<<ci::grid_blocks(N_, v.max_blocks), kBlock, 0, s>>>(
        args_, v.pos[b], v.vel[b], v.pos[1 - b], v.vel[1 - b], v.fin, v.ball + b,
        v.ball + (1 - b), v.nonfinite, dt);
  }

  const int N_;
  const unsigned effects_;
  const ForceKernel force_;
  R* f_ = nullptr;
  V3<R>* fb_ = nullptr;
  R* acc_ = nullptr;  // 3 sums, then the ticket in the fourth slot
  VvArgs args_{};
  bool primed_ = false;
  FrameInputs<R> fin_{};
};

}  // namespace

template <>
std::unique_ptr<CudaIntegrator<CB_REAL>> make_cuda_verlet<CB_REAL>(const Config& c) {
  return std::make_unique<CudaVerlet>(c);
}

}  // namespace cb
