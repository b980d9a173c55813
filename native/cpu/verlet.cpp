// Velocity Verlet on the CPU backend (see core/integrators.hpp for the scheme). Per substep
// a node-local drift pass (not specialised) and one effect-specialised force-and-kick pass;
// F is kept per node between substeps and recomputed (a kick with dt = 0) whenever the
// state, the ball, the hands or the wind changed. Compiled once per real type (CB_REAL).
#include <omp.h>

#include <array>
#include <cstring>
#include <utility>
#include <vector>

#include "core/backend.hpp"
#include "core/integrators.hpp"
#include "cpu/integrators.hpp"

namespace cb {
namespace {

template <class R>
class CpuVerlet;
template <class R>
using VerletRun = void (*)(CpuVerlet<R>&, CpuView<R>&, int, R, bool);

template <class R>
class CpuVerlet final : public CpuIntegrator<R> {
 public:
  explicit CpuVerlet(const Config& c)
      : N_(c.n * c.n), f_(3 * size_t(N_), R(0)),
        gamma_((c.effects & DAMPING) ? R(c.damping / c.node_mass) : R(0)),
        gamma_b_((c.effects & BALL) ? R(c.ball_damping / c.ball_mass) : R(0)),
        run_(dispatch_table<VerletRun<R>, Entry>()[c.effects & (kNumEffectSets - 1)]) {}

  void invalidate() override { primed_ = false; }

  void frames(CpuView<R>& v, int frames, int substeps, R dt) override {
    // F depends on the hands (coupling) and the wind too: recompute it when they moved.
    const bool prime = !primed_ || std::memcmp(&v.fin, &fin_, sizeof fin_) != 0;
    fin_ = v.fin;
    primed_ = true;
    run_(*this, v, frames * substeps, dt, prime);
  }

  template <unsigned E>
  static void run(CpuVerlet& s, CpuView<R>& v, int total, R dt, bool prime) {
    const int n = v.p.n, N = n * n, nt = v.threads;
    const Planes<R> F{s.f_.data(), s.f_.data() + N, s.f_.data() + 2 * size_t(N)};
    TeamSums<R, 3> sums(nt);
    R check_all = 0;
#pragma omp parallel num_threads(nt)
    {
      const int tid = omp_get_thread_num();
      const Params<R> p = vv_params(v.p);
      const FrameInputs<R> fin = v.fin;
      const R gamma = s.gamma_;
      R check = 0;
      for (int st = prime ? -1 : 0; st < total; ++st) {
        const int cur = *v.cur;
        const Planes<R> P = v.pos[cur], V = v.vel[cur], P2 = v.pos[1 - cur], V2 = v.vel[1 - cur];
        const R h = st < 0 ? R(0) : dt;  // st = -1: the priming pass, F only
        if (st >= 0) {
#pragma omp for schedule(static)
          for (int q = 0; q < N; ++q) {
            V3<R> x = P.get(q), u = V.get(q);
            vv_drift(x, u, F.get(q), node_inv_mass(p.inv_mass, n, q), gamma, dt);
            P.set(q, x);
            V.set(q, u);
          }
          if constexpr ((E & BALL) != 0) {
#pragma omp single
            vv_drift(v.ball->p, v.ball->v, s.fb_, p.ball_inv_mass, s.gamma_b_, dt);
          }
        }
        const V3<R> ball_p = v.ball->p;
        R mine[3] = {R(0), R(0), R(0)};
        auto add = [&](V3<R> c) { mine[0] += c.x; mine[1] += c.y; mine[2] += c.z; };
        grid_rows<2>(
            n,
            [&](int i, int j) { add(vv_force_node<R, E, false>(p, P, V, P2, V2, F, fin, ball_p, i, j, gamma, h, check)); },
            [&](int i, int j) { add(vv_force_node<R, E, true>(p, P, V, P2, V2, F, fin, ball_p, i, j, gamma, h, check)); });
        R tot[3];
        sums.reduce(tid, nt, mine, tot);
#pragma omp single
        {
          if constexpr ((E & BALL) != 0) {
            s.fb_ = vv_ball_force<R>(p, {tot[0], tot[1], tot[2]});
            v.ball->v = vv_kick(v.ball->v, s.fb_, p.ball_inv_mass, s.gamma_b_, h);
          }
          *v.cur = 1 - cur;
        }
      }
#pragma omp atomic
      check_all += check;
    }
    note_finite(v, check_all);
  }

 private:
  template <unsigned E>
  struct Entry {
    static constexpr VerletRun<R> fn = &CpuVerlet::run<E>;
  };

  const int N_;
  std::vector<R> f_;  // F per node, 3 planes: the next substep's opening kick
  V3<R> fb_{R(0), R(0), R(0)};  // the ball's F
  const R gamma_, gamma_b_;
  const VerletRun<R> run_;
  bool primed_ = false;
  FrameInputs<R> fin_{};  // the inputs F was computed with
};

}  // namespace

template <>
std::unique_ptr<CpuIntegrator<CB_REAL>> make_cpu_verlet<CB_REAL>(const Config& c) {
  return std::make_unique<CpuVerlet<CB_REAL>>(c);
}

}  // namespace cb
