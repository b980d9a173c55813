// Linearised implicit Euler on the CPU backend (see core/integrators.hpp): per substep an
// effect-specialised right-hand-side pass, then Jacobi-preconditioned CG whose operator
// pass is specialised on the stiffness effects only (16 sets), with OpenMP reductions in a
// fixed order. Compiled once per real type (CB_REAL).
#include <omp.h>

#include <algorithm>
#include <array>
#include <utility>
#include <vector>

#include "core/backend.hpp"
#include "core/integrators.hpp"
#include "cpu/integrators.hpp"

namespace cb {
namespace {

template <class R>
class CpuImplicit;
template <class R>
using ImplicitRun = void (*)(CpuImplicit<R>&, CpuView<R>&, int, R);
// One operator pass by this thread's share of the rows: adds the contact part of K p and
// p . A p to sums[0..3].
template <class R>
using ApplyFn = void (*)(const Params<R>&, const Planes<R>&, const CgVectors<R>&, int, bool, R,
                         V3<R>, V3<R>, R, R, R (&)[4]);

template <class R, unsigned S>
__attribute__((noinline)) void apply_pass(const Params<R>& p, const Planes<R>& P,
                                          const CgVectors<R>& cg, int from, bool first, R beta,
                                          V3<R> ball_p, V3<R> wb, R a_node, R dt, R (&sums)[4]) {
  auto node = [&](auto interior, int i, int j) {
    V3<R> cj{R(0), R(0), R(0)};
    sums[3] += ie_apply_node<R, S, decltype(interior)::value>(p, P, cg, from, first, beta, ball_p,
                                                              wb, i, j, a_node, dt, cj);
    sums[0] += cj.x; sums[1] += cj.y; sums[2] += cj.z;
  };
  grid_rows<2>(
      p.n, [&](int i, int j) { node(std::false_type{}, i, j); },
      [&](int i, int j) { node(std::true_type{}, i, j); });
}

template <class R>
class CpuImplicit final : public CpuIntegrator<R> {
 public:
  explicit CpuImplicit(const Config& c)
      : N_(c.n * c.n), stride_((size_t(N_) + 1 + 15) / 16 * 16 + 16), buf_(21 * stride_, R(0)),
        m_(c.node_mass), c_((c.effects & DAMPING) ? c.damping : 0.0),
        mb_((c.effects & BALL) ? c.ball_mass : 1.0), cb_((c.effects & BALL) ? c.ball_damping : 0.0),
        max_iter_(std::max(0, c.cg_max_iterations)), tol_(R(c.cg_tolerance)),
        run_(dispatch_table<ImplicitRun<R>, Entry>()[c.effects & (kNumEffectSets - 1)]),
        apply_(dispatch_table<ApplyFn<R>, ApplyEntry, kNumStiffSets>()[stiff_index(
            c.effects & kStiffEffects)]) {
    auto planes = [&](int k) {
      R* b = buf_.data() + size_t(3 * k) * stride_;
      return Planes<R>{b, b + stride_, b + 2 * stride_};
    };
    cg_ = {planes(0), planes(1), planes(2), planes(3), {planes(4), planes(5)}, planes(6)};
  }

  void frames(CpuView<R>& v, int frames, int substeps, R dt) override {
    run_(*this, v, frames * substeps, dt);
  }

  template <unsigned E>
  static void run(CpuImplicit& s, CpuView<R>& v, int total, R dt) {
    const int n = v.p.n, N = n * n, nt = v.threads;
    const R a_node = R(s.m_ + double(dt) * s.c_), a_ball = R(s.mb_ + double(dt) * s.cb_);
    const CgVectors<R> cg = s.cg_;
    TeamSums<R, 11> rhs_sums(nt);
    TeamSums<R, 4> apply_sums(nt);
    TeamSums<R, 2> update_sums(nt);
    R check_all = 0;
    R shared[2];  // the ball row's share of a reduction, from the thread that computed it
#pragma omp parallel num_threads(nt)
    {
      const int tid = omp_get_thread_num();
      const Params<R> p = v.p;
      const FrameInputs<R> fin = v.fin;
      R check = 0;
      for (int st = 0; st < total; ++st) {
        const int cur = *v.cur;
        const Planes<R> P = v.pos[cur], V = v.vel[cur], P2 = v.pos[1 - cur], V2 = v.vel[1 - cur];
        const Ball<R> ball = *v.ball;
        RhsSums<R> mine{};
        grid_rows<2>(
            n,
            [&](int i, int j) { ie_rhs_node<R, E, false>(p, P, V, cg, fin, ball.p, ball.v, i, j, a_node, dt, mine); },
            [&](int i, int j) { ie_rhs_node<R, E, true>(p, P, V, cg, fin, ball.p, ball.v, i, j, a_node, dt, mine); });
        const R part[11] = {mine.contact.x, mine.contact.y, mine.contact.z, mine.cj.x, mine.cj.y,
                            mine.cj.z, mine.cd.x, mine.cd.y, mine.cd.z, mine.bb, mine.rz};
        R t[11];
        rhs_sums.reduce(tid, nt, part, t);
#pragma omp single
        {
          RhsSums<R> all{{t[0], t[1], t[2]}, {t[3], t[4], t[5]}, {t[6], t[7], t[8]}, R(0), R(0)};
          shared[0] = shared[1] = R(0);
          ie_rhs_ball<R, E>(p, cg, ball, all, a_ball, dt, N, shared[0], shared[1]);
        }
        const R bb = t[9] + shared[0];
        R rz = t[10] + shared[1], rz_prev = R(1), pap_prev = R(0), rr = R(0);
        int from = 0;
        for (int k = 0; k < s.max_iter_; ++k) {
          if (cg_stopped(k, bb, pap_prev, rr, s.tol_)) break;
          const bool first = k == 0;
          const R beta = first ? R(0) : rz / rz_prev;
          const V3<R> wb = cg_direction(cg, from, N, first, beta);
          R ap[4] = {R(0), R(0), R(0), R(0)};
          s.apply_(p, P, cg, from, first, beta, ball.p, wb, a_node, dt, ap);
          R ta[4];
          apply_sums.reduce(tid, nt, ap, ta);
#pragma omp single
          shared[0] = ie_apply_ball(cg, from, first, beta, V3<R>{ta[0], ta[1], ta[2]}, a_ball, dt, N);
          const R pap = ta[3] + shared[0];
          pap_prev = pap;
          if (!(pap > R(0))) break;  // not definite along p: keep what we have
          const R alpha = rz / pap;
          R up[2] = {R(0), R(0)};
#pragma omp for schedule(static)
          for (int q = 0; q <= N; ++q) ie_update_entry(cg, 1 - from, q, alpha, up[0], up[1]);
          R tu[2];
          update_sums.reduce(tid, nt, up, tu);
          rr = tu[0];
          rz_prev = rz;
          rz = tu[1];
          from = 1 - from;
        }
#pragma omp for schedule(static)
        for (int q = 0; q < N; ++q) ie_finish_node(cg, P, V, P2, V2, q, dt, check);
#pragma omp single
        {
          if constexpr ((E & BALL) != 0) *v.ball = ie_finish_ball(cg, ball, N, dt);
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
    static constexpr ImplicitRun<R> fn = &CpuImplicit::run<E>;
  };
  template <unsigned I>
  struct ApplyEntry {
    static constexpr ApplyFn<R> fn = &apply_pass<R, stiff_set(I)>;
  };

  const int N_;
  const size_t stride_;
  std::vector<R> buf_;  // the CG vectors, N + 1 entries (the ball last) of 3 planes each
  CgVectors<R> cg_{};
  const double m_, c_, mb_, cb_;
  const int max_iter_;
  const R tol_;
  const ImplicitRun<R> run_;
  const ApplyFn<R> apply_;
};

}  // namespace

template <>
std::unique_ptr<CpuIntegrator<CB_REAL>> make_cpu_implicit<CB_REAL>(const Config& c) {
  return std::make_unique<CpuImplicit<CB_REAL>>(c);
}

}  // namespace cb
